"""MAVLink 2 message signing on the simulated vehicles, from a plain pymavlink ground station
(issue 25, item 8).

``beehave sim --mavlink-key-file FILE`` runs in a subprocess; the ground station with the
right key, one with a wrong key and one without any are pymavlink alone (no beehave import
for what is checked on the wire). Expected behaviour is ArduPilot's (GCS_Signing.cpp): a
vehicle with a key signs what it sends, takes only messages signed with that key (RADIO
and RADIO_STATUS, which a telemetry radio injects, also unsigned), drops the rest with a
log line, rejects a replayed signature, and takes a new key with SETUP_SIGNING (signed
with the current one) unless armed.
"""

from __future__ import annotations

import hashlib
import os
import socket
import subprocess
import sys
import threading
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest

os.environ.setdefault("MAVLINK20", "1")
from pymavlink import mavutil  # type: ignore[import-untyped]  # noqa: E402

from beehave.testing import WALL_TIMEOUT_S, wait_until  # noqa: E402  (timeouts only)
from tests.test_mavlink_ground_station import GroundStation, free_port_pair  # noqa: E402

pytestmark = pytest.mark.xdist_group("test_mavlink_signing")

mav = mavutil.mavlink
ROOT = Path(__file__).resolve().parents[1]
PASSPHRASE = "correct horse battery staple"
KEY = hashlib.sha256(PASSPHRASE.encode()).digest()  # MAVProxy's `signing setup PASSPHRASE`
WRONG_KEY = hashlib.sha256(b"not the key").digest()
GUIDED = 15  # ArduRover's mode number
SET_MODE = 11  # the command id ArduPilot acknowledges SET_MODE with
WORLD = """\
name: signed
floor: {size_m: [6, 4]}
robots:
  - {namespace: rover1, kind: kobuki, start: {x_m: 2, y_m: 2}}
"""


class SignedStation(GroundStation):
    """The ground station of the link: listens where the vehicle sends, signs with
    ``key`` and (no unsigned callback) takes only messages signed with it."""

    def __init__(self, port: int, key: bytes) -> None:
        self.key = key
        super().__init__(port)

    def _read(self) -> None:
        self.conn.setup_signing(self.key, sign_outgoing=True)
        super()._read()


@dataclass
class Rig:
    proc: subprocess.Popen[str]
    gcs: SignedStation
    vehicle_port: int
    output: list[str]

    def intruder(self, key: bytes | None) -> Any:
        """Another sender on the vehicle's port: unsigned, or signed with ``key``."""
        conn = mavutil.mavlink_connection(f"udpout:127.0.0.1:{self.vehicle_port}",
                                          source_system=254, source_component=190)
        if key is not None:
            conn.setup_signing(key, sign_outgoing=True)
        return conn

    def wait_logged(self, line: str) -> str:
        """The vehicle's output once it holds ``line`` (the log goes through a pipe and a
        reader thread: it may come after the vehicle's next answer on the link)."""
        assert wait_until(lambda: line in "".join(self.output)), "".join(self.output)
        return "".join(self.output)

    def arm_state(self) -> bool:
        beat = self.gcs.wait("HEARTBEAT", since=self.gcs.mark())
        return bool(beat.base_mode & mav.MAV_MODE_FLAG_SAFETY_ARMED)

    def ordered_after(self) -> None:
        """A signed command of the station, answered: everything sent to the vehicle
        before it has been handled (one socket, read in order) -- the bound of every
        "was ignored" check here."""
        result = self.gcs.command(mav.MAV_CMD_REQUEST_MESSAGE,
                                  mav.MAVLINK_MSG_ID_AUTOPILOT_VERSION)
        assert result == mav.MAV_RESULT_ACCEPTED


@pytest.fixture(scope="module")
def rig(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Rig]:
    folder = tmp_path_factory.mktemp("signing")
    world, key_file = folder / "signed.yaml", folder / "mavlink.key"
    world.write_text(WORLD)
    key_file.write_text(PASSPHRASE + "\n")
    base = free_port_pair()
    proc = subprocess.Popen(
        [sys.executable, "-m", "beehave.cli", "sim", str(world), "--mavlink-base-port",
         str(base), "--mavlink-key-file", str(key_file), "--no-lockstep"],
        cwd=ROOT, env={**os.environ, "PYTHONPATH": str(ROOT)}, stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT, text=True)
    output: list[str] = []

    def read() -> None:
        for line in proc.stdout or ():
            output.append(line)

    reader = threading.Thread(target=read, daemon=True)
    reader.start()
    gcs: SignedStation | None = None
    try:
        gcs = SignedStation(base, KEY)  # its first signed HEARTBEAT: the vehicle signs
        vehicle_port = next(iter(gcs.conn.clients))[1]  # where the HEARTBEAT came from
        yield Rig(proc, gcs, vehicle_port, output)
        assert proc.poll() is None, "".join(output)
    finally:
        if gcs is not None:
            gcs.close()
        proc.terminate()
        proc.wait(timeout=WALL_TIMEOUT_S)
        reader.join(WALL_TIMEOUT_S)


def test_the_vehicle_signs_and_a_station_with_the_key_flies_it(rig: Rig) -> None:
    beat = rig.gcs.wait("HEARTBEAT", since=rig.gcs.mark())
    assert beat.get_signed()  # a signature this station checked with its key
    assert rig.gcs.command(mav.MAV_CMD_COMPONENT_ARM_DISARM, 1) == mav.MAV_RESULT_ACCEPTED
    assert rig.arm_state()
    assert rig.gcs.command(mav.MAV_CMD_COMPONENT_ARM_DISARM, 0) == mav.MAV_RESULT_ACCEPTED
    assert not rig.arm_state()
    # Every message carries a signature; a parser without the key still reads it (signing
    # authenticates, it does not encrypt).
    raw = bytes(beat.get_msgbuf())
    assert raw[0] == mav.PROTOCOL_MARKER_V2 and raw[2] & mav.MAVLINK_IFLAG_SIGNED
    assert mav.MAVLink(None).decode(bytearray(raw)).get_type() == "HEARTBEAT"


@pytest.mark.parametrize(("key", "logged"), [(None, "unsigned"), (WRONG_KEY, "wrongly signed")],
                         ids=["unsigned", "wrong-key"])
def test_commands_unsigned_or_signed_with_another_key_are_ignored_with_a_log(
        rig: Rig, key: bytes | None, logged: str) -> None:
    intruder = rig.intruder(key)
    try:
        since = rig.gcs.mark()
        intruder.mav.command_long_send(1, 1, mav.MAV_CMD_COMPONENT_ARM_DISARM, 0,
                                       1, 0, 0, 0, 0, 0, 0)
        intruder.mav.set_mode_send(1, mav.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, GUIDED)
        rig.ordered_after()
        acks = [m for m in rig.gcs.messages[since:] if m.get_type() == "COMMAND_ACK"
                and m.command in (mav.MAV_CMD_COMPONENT_ARM_DISARM, SET_MODE)]
        assert acks == []  # no answer: the vehicle never took them
        beat = rig.gcs.wait("HEARTBEAT", since=rig.gcs.mark())
        assert not beat.base_mode & mav.MAV_MODE_FLAG_SAFETY_ARMED
        assert beat.custom_mode != GUIDED
    finally:
        intruder.close()
    rig.wait_logged(f"ignored {'an' if key is None else 'a'} {logged} COMMAND_LONG from "
                    f"system 254")


def test_radio_status_is_taken_unsigned_as_ardupilot_does(rig: Rig) -> None:
    intruder = rig.intruder(None)
    try:
        intruder.mav.radio_status_send(200, 190, 90, 10, 12, 0, 0)
        intruder.mav.param_request_read_send(1, 1, b"WP_SPEED", -1)
        rig.ordered_after()
    finally:
        intruder.close()
    # The vehicle logs in the order it reads: a refused RADIO_STATUS would come first.
    text = rig.wait_logged("ignored an unsigned PARAM_REQUEST_READ from system 254")
    assert "RADIO_STATUS" not in text  # taken


def test_a_replayed_signed_command_is_ignored(rig: Rig) -> None:
    """An eavesdropper who recorded a signed ARM sends it again: its timestamp is not newer
    than what the vehicle has seen from that stream, so it is dropped."""
    msg = rig.gcs.conn.mav.command_long_encode(1, 1, mav.MAV_CMD_COMPONENT_ARM_DISARM, 0,
                                               1, 0, 0, 0, 0, 0, 0)
    raw = msg.pack(rig.gcs.conn.mav)  # signed: the station's next signature timestamp
    rig.gcs.conn.mav.seq = (rig.gcs.conn.mav.seq + 1) % 256
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as eavesdropper:
        since = rig.gcs.mark()
        eavesdropper.sendto(raw, ("127.0.0.1", rig.vehicle_port))
        rig.gcs.wait("COMMAND_ACK", lambda a: a.command == mav.MAV_CMD_COMPONENT_ARM_DISARM,
                     since=since)
        assert rig.arm_state()
        assert rig.gcs.command(mav.MAV_CMD_COMPONENT_ARM_DISARM, 0) == mav.MAV_RESULT_ACCEPTED
        since = rig.gcs.mark()
        eavesdropper.sendto(raw, ("127.0.0.1", rig.vehicle_port))  # the replay
        rig.ordered_after()
    acks = [m for m in rig.gcs.messages[since:] if m.get_type() == "COMMAND_ACK"
            and m.command == mav.MAV_CMD_COMPONENT_ARM_DISARM]
    assert acks == [] and not rig.arm_state()
    rig.wait_logged("ignored a wrongly signed COMMAND_LONG from system 255")


def test_setup_signing_changes_the_key_but_not_while_armed(rig: Rig) -> None:
    new_key = hashlib.sha256(b"the next key").digest()
    gcs = rig.gcs
    assert gcs.command(mav.MAV_CMD_COMPONENT_ARM_DISARM, 1) == mav.MAV_RESULT_ACCEPTED
    since = gcs.mark()
    gcs.send(lambda m: m.setup_signing_send(1, 1, list(new_key), 0))
    said = gcs.wait("STATUSTEXT", lambda s: "signing" in s.text, since=since)
    assert "armed" in said.text
    assert gcs.command(mav.MAV_CMD_COMPONENT_ARM_DISARM, 0) == mav.MAV_RESULT_ACCEPTED
    try:
        gcs.send(lambda m: m.setup_signing_send(1, 1, list(new_key), 0))
        # From now on the vehicle signs with the new key: this station, still on the old
        # one, drops what it sends; on the new key it hears the vehicle again.
        since = gcs.mark()
        gcs.conn.setup_signing(new_key, sign_outgoing=True)
        beat = gcs.wait("HEARTBEAT", since=since)
        assert beat.get_signed()
        assert gcs.command(mav.MAV_CMD_REQUEST_MESSAGE,
                           mav.MAVLINK_MSG_ID_AUTOPILOT_VERSION) == mav.MAV_RESULT_ACCEPTED
    finally:  # back to the file's key for the other tests of the module
        gcs.send(lambda m: m.setup_signing_send(1, 1, list(KEY), 0))
        gcs.conn.setup_signing(KEY, sign_outgoing=True)
        since = gcs.mark()
        gcs.wait("HEARTBEAT", since=since)


@pytest.mark.parametrize(("content", "says"), [
    (None, "cannot be read"),
    ("   \n", "is empty"),
])
def test_a_key_file_that_cannot_be_used_is_refused_naming_it(
        tmp_path: Path, content: str | None, says: str) -> None:
    key_file = tmp_path / "mavlink.key"
    if content is not None:
        key_file.write_text(content)
    world = tmp_path / "signed.yaml"
    world.write_text(WORLD)
    done = subprocess.run(
        [sys.executable, "-m", "beehave.cli", "sim", str(world), "--mavlink-key-file",
         str(key_file), "--duration-s", "1"],
        cwd=ROOT, env={**os.environ, "PYTHONPATH": str(ROOT)}, capture_output=True,
        text=True, timeout=WALL_TIMEOUT_S)
    assert done.returncode == 2, done
    assert str(key_file) in done.stderr and says in done.stderr, done.stderr


# ---- beehave's side: the MAVLink HALs and actions on a signed link ---------------------------

def test_beehave_links_sign_with_their_key_file_and_drop_what_is_not_signed(
        tmp_path: Path) -> None:
    """A link (the HALs' and actions') with ``signing_key_file`` flies a vehicle with that
    key; towards a vehicle that does not sign it hears nothing (dropped, counted); a link
    without the key hears a signing vehicle but cannot command it."""
    from beehave.errors import ConfigError, MavlinkError
    from hal.mavlink import MavlinkPositionHAL, close_all_links, open_link
    from robots.mavlink_endpoint import MavlinkEndpoint, free_udp_ports
    from robots.sim import Simulation
    from robots.world import world_from_dict

    key_file = tmp_path / "mavlink.key"
    key_file.write_text(KEY.hex())  # 64 hex digits: the key itself
    world = {"name": "two", "floor": {"size_m": [6, 4]},
             "robots": [{"namespace": "signed", "kind": "kobuki", "start": {"x_m": 1, "y_m": 1}},
                        {"namespace": "plain", "kind": "kobuki", "start": {"x_m": 4, "y_m": 3}}]}
    sim = Simulation(world_from_dict(world), real_time_factor=1.0)
    ports = free_udp_ports(3)
    signed = MavlinkEndpoint(sim, "signed", url=f"udpout:127.0.0.1:{ports[0]}", system_id=1,
                             signing_key=KEY)
    plain = MavlinkEndpoint(sim, "plain", url=f"udpout:127.0.0.1:{ports[1]}", system_id=2)
    sim.start()
    try:
        link = open_link(f"udp:127.0.0.1:{ports[0]}", signing_key_file=str(key_file))
        link.wait_heartbeat(timeout_s=WALL_TIMEOUT_S)
        link.arm(True)
        assert signed.armed
        link.arm(False)
        assert not any("signed" in reason for reason in signed.ignored), signed.ignored
        with pytest.raises(ConfigError, match="signing_key_file"):  # one link, one key
            open_link(f"udp:127.0.0.1:{ports[0]}", signing_key_file=str(tmp_path / "other"))
        # A signing link towards a vehicle that does not sign: nothing is taken.
        deaf = open_link(f"udp:127.0.0.1:{ports[1]}", signing_key_file=str(key_file))
        with pytest.raises(MavlinkError):
            deaf.wait_heartbeat(timeout_s=3.0)  # the vehicle sends 1 Hz: three were dropped
        assert deaf.ignored["unsigned message"] >= 2, deaf.ignored
        # The vehicle with the key, commanded by a link without it: heard, not obeyed.
        signed_port = ports[0]
        close_all_links()
        keyless = open_link(f"udp:127.0.0.1:{signed_port}")
        keyless.wait_heartbeat(timeout_s=WALL_TIMEOUT_S)
        with pytest.raises(MavlinkError):
            keyless.arm(True)
        assert not signed.armed and signed.ignored["unsigned COMMAND_LONG"] >= 1
        # A HAL names its key file; a bad one is refused when the HAL is made.
        with pytest.raises(ConfigError, match="cannot be read"):
            MavlinkPositionHAL(connection=f"udp:127.0.0.1:{ports[2]}",
                               signing_key_file=str(tmp_path / "missing.key"))
    finally:
        close_all_links()
        signed.close()
        plain.close()
        sim.close()
