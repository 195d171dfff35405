"""The contract every HAL plugin keeps. Inherit it in the plugin's test module::

    from hal_contract import HALContract

    class TestMyHAL(HALContract):
        hal_cls = MyHAL
        expected_keys = ("battery/percentage",)

        def hal_params(self) -> dict[str, Any]:   # optional: constructor parameters
            return {"port": "/dev/null"}
"""

from __future__ import annotations

import asyncio
import importlib.metadata
import json
from collections.abc import Awaitable, Callable
from typing import Any, ClassVar, TypeVar

from beehave.blackboard import Blackboard
from beehave.events import Event, EventBus, EventKind
from beehave.hal import ENTRY_POINT_GROUP, HAL, HALManager
from beehave.status import Status

T = TypeVar("T")


class HALContract:
    """Contract tests for one HAL class; not collected by itself (no ``Test`` prefix)."""

    hal_cls: ClassVar[type[HAL]]
    expected_keys: ClassVar[tuple[str, ...]] = ()
    """Blackboard keys the HAL must publish once loaded (and keep fresh while it runs)."""
    entry_point: ClassVar[str | None] = None
    """The name under ``beehave.hals`` the HAL is published as, if any."""

    def hal_params(self) -> dict[str, Any]:
        return {}

    def configure(self, manager: HALManager) -> None:
        """Give the manager what the HAL needs besides its parameters (e.g. a ROS node in
        ``manager.node``); called before the HAL is registered."""

    # -- helpers ---------------------------------------------------------------------------

    def run_with_manager(self, body: Callable[[HALManager, list[Event]], Awaitable[T]]) -> T:
        async def main() -> T:
            events: list[Event] = []
            bus = EventBus()
            bus.subscribe(events.append)
            manager = HALManager(Blackboard(), events=bus, backoff_initial_s=0.01,
                                 backoff_max_s=0.05)
            self.configure(manager)
            manager.register(self.hal_cls, **self.hal_params())
            try:
                return await asyncio.wait_for(body(manager, events), 10)
            finally:
                await manager.close()
                manager.blackboard.unbind()
                leftover = asyncio.all_tasks() - {asyncio.current_task()}
                assert not leftover, f"tasks left by HAL {self.hal_cls.name!r}: {leftover}"
        return asyncio.run(main())

    @staticmethod
    async def settle(turns: int = 20) -> None:
        """Let the HAL's run() take a few steps."""
        for _ in range(turns):
            await asyncio.sleep(0)

    # -- the contract ----------------------------------------------------------------------

    def test_has_a_name(self) -> None:
        assert isinstance(self.hal_cls.name, str) and self.hal_cls.name
        assert issubclass(self.hal_cls, HAL)

    def test_loads_runs_and_reports_started(self) -> None:
        async def body(manager: HALManager, events: list[Event]) -> None:
            hal = await manager.load(self.hal_cls.name)
            await self.settle()
            assert isinstance(hal, self.hal_cls)
            assert hal.status is Status.RUNNING and hal.error is None
            assert manager.loaded == {self.hal_cls.name: hal}
            assert any(e.kind is EventKind.STARTED and e.subject == f"hal:{hal.name}"
                       for e in events)
        self.run_with_manager(body)

    def test_publishes_its_keys_fresh_and_as_its_writer(self) -> None:
        async def body(manager: HALManager, events: list[Event]) -> None:
            hal = await manager.load(self.hal_cls.name)
            await self.settle()
            for key in self.expected_keys:
                entry = manager.blackboard.entry(key)
                assert entry is not None, f"HAL {hal.name!r} did not publish {key!r}"
                assert entry.writer == f"hal:{hal.name}" and not entry.stale
        self.run_with_manager(body)

    def test_one_shared_instance_stopped_with_its_safe_state_after_the_last_release(
            self) -> None:
        async def body(manager: HALManager, events: list[Event]) -> None:
            owner_a, owner_b = object(), object()
            first = await manager.load(self.hal_cls.name, owner=owner_a)
            second = await manager.load(self.hal_cls.name, owner=owner_b)
            again = await manager.load(self.hal_cls.name, owner=owner_a)
            assert first is second is again
            assert manager.refs(self.hal_cls.name) == 2
            await manager.release(self.hal_cls.name, owner=owner_a)
            assert first.status is Status.RUNNING
            await manager.release(self.hal_cls.name, owner=owner_b)
            assert first.status is Status.INTERRUPTED
            assert manager.loaded == {}
            assert not any(e.kind is EventKind.SAFE_STATE_FAILED for e in events)
        self.run_with_manager(body)

    def test_entries_read_as_stale_after_unload(self) -> None:
        async def body(manager: HALManager, events: list[Event]) -> None:
            await manager.load(self.hal_cls.name)
            await self.settle()
            await manager.release(self.hal_cls.name)
            for key in self.expected_keys:
                assert manager.blackboard.is_stale(key), key
        self.run_with_manager(body)

    def test_can_be_loaded_again_after_unload(self) -> None:
        async def body(manager: HALManager, events: list[Event]) -> None:
            first = await manager.load(self.hal_cls.name)
            await manager.release(self.hal_cls.name)
            second = await manager.load(self.hal_cls.name)
            await self.settle()
            assert second is not first and second.status is Status.RUNNING
            for key in self.expected_keys:
                assert not manager.blackboard.is_stale(key), key
        self.run_with_manager(body)

    def test_snapshot_is_json_serialisable(self) -> None:
        async def body(manager: HALManager, events: list[Event]) -> None:
            await manager.load(self.hal_cls.name)
            await self.settle()
            json.dumps(manager.snapshot())
            json.dumps(manager.blackboard.snapshot())
            assert manager.snapshot()[self.hal_cls.name]["status"] == "RUNNING"
        self.run_with_manager(body)

    def test_found_through_its_entry_point(self) -> None:
        if self.entry_point is None:
            return  # not published as a plugin: nothing to check
        eps = {ep.name: ep for ep in importlib.metadata.entry_points(group=ENTRY_POINT_GROUP)}
        assert self.entry_point in eps, f"{self.entry_point!r} not in {sorted(eps)}"
        assert eps[self.entry_point].load() is self.hal_cls
        assert HALManager().resolve(self.entry_point)[0] is self.hal_cls
