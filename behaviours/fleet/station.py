"""A charging station agent: one robot at a time, by a leased reservation.

    python -m behaviours.fleet.station NAME [--world factory] [--station charger1]

It registers ``charging`` with ``{"station": <the world's station>, "holder": <robot or
null>}`` and answers FIPA requests of protocol ``charging`` whose content is
``{"op": "reserve" | "renew" | "release", "lease_s": L}``:

- ``reserve``: granted (inform ``{"result": {"station", "holder", "lease_s"}}``) when the
  place is free, when the holder's lease ran out, when the holder left the directory, or
  to the holder itself;
  otherwise refused naming the holder.
- ``renew``: the holder extends its lease by ``lease_s``; anyone else is refused.
- ``release``: the holder frees the place. Idempotent: a release from a robot that holds
  nothing (its lease lapsed while it stopped) is agreed to and changes nothing.

The station does not know where robots physically are: a robot that keeps its lease but
charges elsewhere is the robot's bug, and ``beehave fleet`` checks in the physics that no
two robots ever charged at one station at once.
"""

from __future__ import annotations

import argparse
import math
import time
from typing import Any

from beehave.agents import Message
from beehave.agents.protocols import RequestResponder
from behaviours.fleet.process import add_trust_options, say, serve
from behaviours.fleet.site import site

PROTOCOL = "charging"
MAX_LEASE_S = 60.0


class Reservations(RequestResponder):
    """The station's behaviour: answers reservation requests (see the module docstring)."""

    protocol = PROTOCOL
    service = "charging"

    def __init__(self, station: str) -> None:
        self.station = station
        self.holder: str | None = None
        self.until = -math.inf  # time.monotonic() the lease ends

    def service_properties(self) -> dict[str, Any]:
        return {"station": self.station, "holder": self.holder}

    def _publish(self) -> None:
        self.agent.register("charging", **self.service_properties())

    def _free_if_lapsed(self) -> None:
        if self.holder is None:
            return
        if time.monotonic() > self.until or self.agent.directory.get(self.holder) is None:
            say("lapsed", station=self.station, holder=self.holder)
            self.holder = None
            self._publish()

    def refuse(self, message: Message) -> str | None:
        content = message.content
        if not isinstance(content, dict) or content.get("op") not in ("reserve", "renew",
                                                                       "release"):
            return (f"content must be {{'op': 'reserve' | 'renew' | 'release', 'lease_s': "
                    f"seconds}}, got {content!r:.120}")
        lease = content.get("lease_s", 10.0)
        if (isinstance(lease, bool) or not isinstance(lease, (int, float))
                or not 0 < lease <= MAX_LEASE_S):
            return f"lease_s must be a number in (0, {MAX_LEASE_S:g}], got {lease!r}"
        self._free_if_lapsed()
        op, sender = content["op"], message.sender
        if op == "reserve" and self.holder not in (None, sender):
            return f"{self.station} is reserved by {self.holder}"
        if op == "renew" and self.holder != sender:
            return f"{sender} holds no reservation at {self.station} (holder: {self.holder})"
        # A release is idempotent: one whose lease lapsed already (a robot stopping, or
        # slow) wants what is true, the station free of it; it frees nobody else's.
        return None

    def perform(self, task: Message) -> Any:
        op, sender = task.content["op"], task.sender
        lease_s = float(task.content.get("lease_s", 10.0))
        if op == "release":
            if self.holder == sender:
                self.holder = None
                say("released", station=self.station, holder=sender)
            else:
                say("nothing_to_release", station=self.station, sender=sender,
                    holder=self.holder)
        else:
            if self.holder != sender:
                say("reserved", station=self.station, holder=sender)
            self.holder = sender
            self.until = time.monotonic() + lease_s
        self._publish()
        return {"station": self.station, "holder": self.holder, "lease_s": lease_s}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m behaviours.fleet.station",
                                     description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("name", help="the agent's name")
    parser.add_argument("--world", default="factory")
    parser.add_argument("--station", default=None,
                        help="the world's charging station it runs (default: NAME)")
    parser.add_argument("--lease-s", type=float, default=2.0, help="its directory lease")
    add_trust_options(parser)
    args = parser.parse_args(argv)
    station = args.station or args.name
    stations = site(args.world).stations
    if station not in stations:
        parser.error(f"no charging station {station!r} in world {args.world!r}; "
                     f"it has {sorted(stations)}")
    return serve(args.name, Reservations, {"station": station}, lease_s=args.lease_s, args=args)


if __name__ == "__main__":
    raise SystemExit(main())
