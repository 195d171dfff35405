"""The WebSocket fan-out (``beehave.interfaces.http.hub``) without a server: what a client
that keeps up, a slow client and the blackboard's encoding get."""

from __future__ import annotations

import asyncio
import json
import time
from typing import Any

import pytest

pytest.importorskip("fastapi")

from beehave import Blackboard  # noqa: E402
from beehave.interfaces.http.hub import Client, Update, _BoardCache, _message  # noqa: E402


def update(seq: int, events: list[dict[str, Any]] | None = None) -> Update:
    body = f'"seq":{seq},"snapshot":{{"behavior":"idle"}},"blackboard":{{}}'.encode()
    events = events or []
    return Update("emili1", body, events, _message("emili1", body, events))


def drain(client: Client) -> list[str]:
    return asyncio.run(client.next_messages())


def test_a_client_that_keeps_up_is_sent_the_one_message_built_for_every_client() -> None:
    client = Client(["emili1"], events_kept=10)
    client.offer(update(1))
    first = json.loads(drain(client)[0])  # the first one tells the counts
    assert (first["seq"], first["dropped"], first["events_dropped"]) == (1, 0, 0)
    for seq in (2, 3):
        shared = update(seq, [{"seq": seq, "kind": "switch_completed"}])
        client.offer(shared)
        [sent] = drain(client)
        assert sent is shared.text  # the same string object: no per-client work
        assert json.loads(sent)["events"] == [{"seq": seq, "kind": "switch_completed"}]
        assert "dropped" not in json.loads(sent)  # unchanged counts are not repeated


def test_a_slow_client_gets_the_newest_update_with_every_event_and_its_count() -> None:
    client = Client(["emili1"], events_kept=10)
    client.offer(update(1))
    drain(client)
    client.offer(update(2, [{"seq": 5}]))
    client.offer(update(3, [{"seq": 6}]))  # before 2 was sent: 2 is replaced
    client.offer(update(4))
    [sent] = drain(client)
    message = json.loads(sent)
    assert message["seq"] == 4 and message["snapshot"] == {"behavior": "idle"}
    assert [e["seq"] for e in message["events"]] == [5, 6]  # the replaced ones' events too
    assert (message["dropped"], message["events_dropped"]) == (2, 0)
    assert client.dropped == 2
    shared = update(5)
    client.offer(shared)
    assert drain(client) == [shared.text]  # caught up: the shared message again


def test_a_stalled_client_keeps_the_newest_events_and_counts_the_others() -> None:
    client = Client(["emili1"], events_kept=3)
    client.offer_events("emili1", [{"seq": i} for i in range(1, 6)], upto=5)
    for seq in range(6, 9):
        client.offer(update(seq, [{"seq": seq}]))
    [sent] = drain(client)
    message = json.loads(sent)
    assert [e["seq"] for e in message["events"]] == [6, 7, 8]
    assert message["events_dropped"] == 5 and message["dropped"] == 2


def decoded(cache: _BoardCache) -> dict[str, Any]:
    return json.loads(cache.encode())


def same_as_snapshot(cache: _BoardCache, board: Blackboard) -> None:
    t0 = time.monotonic()
    got, want = decoded(cache), board.snapshot()
    between = time.monotonic() - t0  # the ages were read this far apart
    assert list(got) == list(want)
    for key, entry in want.items():
        ages = got[key].pop("age_s"), entry.pop("age_s")
        assert got[key] == entry, key
        assert (ages[0] is None) == (ages[1] is None), key
        if ages[1] is not None:
            assert abs(ages[0] - ages[1]) <= between + 0.01, (key, ages)


def test_the_streamed_blackboard_is_what_the_blackboard_says_entry_by_entry() -> None:
    board = Blackboard()
    cache = _BoardCache(board, resync_s=3600.0)  # no resync: what the cache keeps itself
    board.subscribe("**", lambda change: cache.written(change.key))
    board.set("battery/percentage", 80.0, writer="hal:battery")
    board.set("scan/front_m", float("inf"), writer="hal:laser")
    same_as_snapshot(cache, board)
    assert decoded(cache)["scan/front_m"]["value"] == {"$float": "inf"}
    board.set("odom/x_m", 1.0, writer="hal:odometry")  # a new key
    board.set("battery/percentage", 79.0, writer="hal:battery")
    same_as_snapshot(cache, board)
    time.sleep(0.2)
    written = time.monotonic()
    board.set("battery/percentage", 79.0, writer="hal:battery")  # same value: age resets
    assert decoded(cache)["battery/percentage"]["age_s"] <= time.monotonic() - written + 0.01
    assert decoded(cache)["odom/x_m"]["age_s"] >= 0.2  # ages move on without a write
    board.set("odom/x_m", 1.0, writer="hal:odometry", stale=True)
    assert decoded(cache)["odom/x_m"]["stale"] is True
    board.declare("scan/front_m", max_age_s=0.05)  # stale by age, with no write at all
    time.sleep(0.1)
    assert decoded(cache)["scan/front_m"]["stale"] is True
    same_as_snapshot(cache, board)


def test_keys_declared_but_never_written_appear_at_the_resync() -> None:
    board = Blackboard()
    cache = _BoardCache(board, resync_s=0.0)  # every build reads the whole board
    board.declare("lift/height_m", max_age_s=1.0)
    assert decoded(cache)["lift/height_m"] == {"value": None, "stamp": None, "stale": True,
                                               "writer": None, "age_s": None}
    same_as_snapshot(cache, board)


def test_a_new_client_gets_each_event_once_backlog_and_updates_overlapping() -> None:
    client = Client(["emili1"], events_kept=10)
    # The backlog holds the events up to seq 5; the pump's next update took 4–6.
    client.offer_events("emili1", [{"seq": i} for i in range(1, 6)], upto=5)
    client.offer(update(1, [{"seq": 4}, {"seq": 5}, {"seq": 6}]))
    [sent] = drain(client)
    assert [e["seq"] for e in json.loads(sent)["events"]] == [1, 2, 3, 4, 5, 6]
    shared = update(2, [{"seq": 7}])
    client.offer(shared)
    assert drain(client) == [shared.text]


class _Plane:
    """What the hub subscribes to, counting subscriptions still open."""

    def __init__(self) -> None:
        self.board = Blackboard()
        self.open = 0

    def subscribe(self, _: Any) -> Any:
        self.open += 1

        def unsubscribe() -> None:
            self.open -= 1
        return unsubscribe


def test_close_ends_the_pump_and_its_subscriptions_when_the_loop_has_gone() -> None:
    # A forced exit skips the lifespan's stop: the server's thread then calls close().
    from beehave.interfaces.http.hub import Hub

    plane = _Plane()
    hub = Hub({"emili1": plane}, rate_hz=50, refresh_s=0.05)  # type: ignore[dict-item]

    async def started() -> None:
        hub.start()
    asyncio.run(started())
    pump = hub._thread
    assert pump is not None and pump.is_alive()
    assert plane.open == 1
    hub.close()
    assert not pump.is_alive()
    assert plane.open == 0
    assert hub._thread is None
    hub.close()  # idempotent


def test_a_turn_reads_the_running_tree_again_only_after_an_event_or_when_it_is_old(
        hl: Any, monkeypatch: pytest.MonkeyPatch) -> None:
    """A driving robot writes its blackboard all the time and starts or ends something
    rarely: its turns re-encode the blackboard, not the tree — until an event comes, whose
    effect is in the very next update."""
    from config_fixtures import Drive

    from beehave.interfaces import ControlPlane
    from beehave.interfaces.http import hub as hub_module
    from beehave.testing import wait_until

    hl.register("drive", Drive, station="dock")
    plane = ControlPlane(hl, name="emili1")
    reads = [0]
    snapshot = plane.snapshot

    def counted() -> dict[str, Any]:
        reads[0] += 1
        return snapshot()

    monkeypatch.setattr(plane, "snapshot", counted)
    monkeypatch.setattr(hub_module, "TREE_MAX_AGE_S", 3600.0)
    hub = hub_module.Hub({"emili1": plane})

    async def started() -> None:
        hub.start()
    asyncio.run(started())
    try:
        def turn() -> dict[str, Any]:
            return json.loads(hub.build("emili1", reuse_tree=True))

        assert turn()["snapshot"]["behavior"] == "idle"
        for i in range(20):
            hl.blackboard.set("odom/x_m", i * 0.1)
            assert turn()["blackboard"]["odom/x_m"]["value"] == i * 0.1
        assert reads[0] == 1
        hl.switch("drive")
        # The switch's events have the tree read again (never because of its age here).
        assert wait_until(lambda: turn()["snapshot"]["behavior"] == "drive")
        assert wait_until(lambda: turn()["snapshot"]["tree"]["children"] != [])
        settled = reads[0]
        turn()
        assert reads[0] == settled
        monkeypatch.setattr(hub_module, "TREE_MAX_AGE_S", 0.0)  # old: read again
        turn()
        assert reads[0] == settled + 1
        assert json.loads(hub.build("emili1"))["snapshot"]["behavior"] == "drive"
        assert reads[0] == settled + 2  # a build of its own reads it fresh
    finally:
        hub.close()
        plane.close()
