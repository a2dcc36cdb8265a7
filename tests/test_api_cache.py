"""The read path's shared pieces: the single-flight cache and the by-vehicle unit index."""

from __future__ import annotations

import asyncio
import time
from typing import Any

import pytest

from eqgw.ingest.events import UnitRef
from eqgw.ingest.faults import FaultTracker
from eqgw.ingest.state import LiveState, UnitState
from eqgw.web.runtime import Runtime


def _runtime() -> Runtime:
    # Only the cache is exercised: nothing else of the runtime is touched.
    none: Any = None
    return Runtime(
        settings=none,
        api=none,
        engine=none,
        ingest=none,
        commands=none,
        keys=none,
        limiter=none,
        audit_log=none,
    )


async def test_concurrent_misses_share_one_load() -> None:
    rt = _runtime()
    loads = 0
    release = asyncio.Event()

    async def load() -> int:
        nonlocal loads
        loads += 1
        await release.wait()
        return loads

    waiters = [asyncio.create_task(rt.cached("x", 60.0, load)) for _ in range(50)]
    await asyncio.sleep(0)
    release.set()
    assert await asyncio.gather(*waiters) == [1] * 50
    assert loads == 1
    assert await rt.cached("x", 60.0, load) == 1  # still fresh: no second load
    assert loads == 1


async def test_expired_entry_is_loaded_again() -> None:
    rt = _runtime()
    calls = 0

    async def load() -> int:
        nonlocal calls
        calls += 1
        return calls

    assert await rt.cached("x", 0.0, load) == 1
    assert await rt.cached("x", 0.0, load) == 2
    assert await rt.cached("y", 60.0, load) == 3  # names do not share entries
    assert await rt.cached("x", 60.0, load) == 4
    # A TTL of 0 is always fresh, stale-while-loading or not.
    got = [await rt.cached("z", 0.0, load, stale_while_loading=True) for _ in range(3)]
    assert got == [5, 6, 7]


async def test_stale_while_loading_serves_the_last_value_during_a_refresh() -> None:
    rt = _runtime()
    calls = 0
    release = asyncio.Event()
    ttl = 0.01

    async def load() -> int:
        nonlocal calls
        calls += 1
        if calls > 1:
            await release.wait()
        return calls

    async def get(fn: Any = load) -> int:
        value: int = await rt.cached("v", ttl, fn, stale_while_loading=True)
        return value

    assert await get() == 1  # nothing cached yet: the first request waits
    await asyncio.sleep(ttl * 2)
    # Expired: the old value at once, one refresh running for all of these requests.
    got = [await get() for _ in range(20)]
    await asyncio.sleep(0)  # the refresh starts
    assert got == [1] * 20 and calls == 2
    release.set()
    await asyncio.sleep(0)
    await asyncio.sleep(0)
    assert await get() == 2

    async def fail() -> int:
        raise RuntimeError("database away")

    # A failed refresh keeps the last value served (and is retried by the next request).
    await asyncio.sleep(ttl * 2)
    assert await get(fail) == 2
    await asyncio.sleep(0)
    assert await get(fail) == 2


async def test_stale_is_served_only_within_max_stale() -> None:
    """A value that expired longer than `max_stale_s` ago is not served: the request waits
    for the fresh one (a page loading after a quiet spell gets current values)."""
    rt = _runtime()
    calls = 0

    async def load() -> int:
        nonlocal calls
        calls += 1
        return calls

    async def get() -> int:
        value: int = await rt.cached("v", 0.01, load, stale_while_loading=True, max_stale_s=0.05)
        return value

    assert await get() == 1
    await asyncio.sleep(0.02)
    assert await get() == 1  # expired within max_stale: the last value, a refresh started
    for _ in range(3):
        await asyncio.sleep(0)  # the refresh runs and is kept
    assert await get() == 2
    await asyncio.sleep(0.2)
    assert await get() == 3  # expired long ago: waits for the fresh value


async def test_a_failed_load_reaches_every_waiter_and_is_not_cached() -> None:
    rt = _runtime()
    release = asyncio.Event()

    async def broken() -> int:
        await release.wait()
        raise RuntimeError("database away")

    waiters = [asyncio.create_task(rt.cached("x", 60.0, broken)) for _ in range(3)]
    await asyncio.sleep(0)
    release.set()
    results = await asyncio.gather(*waiters, return_exceptions=True)
    assert all(isinstance(r, RuntimeError) for r in results)

    async def fine() -> int:
        return 7

    assert await rt.cached("x", 60.0, fine) == 7


async def test_a_cancelled_waiter_does_not_cancel_the_shared_load() -> None:
    rt = _runtime()
    release = asyncio.Event()

    async def load() -> str:
        await release.wait()
        return "ok"

    first = asyncio.create_task(rt.cached("x", 60.0, load))
    second = asyncio.create_task(rt.cached("x", 60.0, load))
    await asyncio.sleep(0)
    first.cancel()
    release.set()
    assert await second == "ok"
    with pytest.raises(asyncio.CancelledError):
        await first


def _unit(vehicle: str, bus: str, sa: int) -> UnitState:
    return UnitState(ref=UnitRef(vehicle, bus, sa), faults=FaultTracker())


def test_units_are_indexed_by_vehicle_through_set_replace_and_delete() -> None:
    live = LiveState()
    a30, a31, b30 = _unit("A", "a/0", 30), _unit("A", "a/0", 31), _unit("B", "b/0", 30)
    for u in (a30, a31, b30):
        live.units[u.ref.key] = u
    assert {id(u) for u in live.of_vehicle("A")} == {id(a30), id(a31)}
    assert live.of_vehicle("B") == [b30]
    assert live.of_vehicle("C") == []
    assert live.vehicle_ids() == {"A", "B"}

    # The same (bus, SA) given to another vehicle (a bus re-mapped in configuration).
    moved = _unit("C", "a/0", 31)
    live.units[moved.ref.key] = moved
    assert live.of_vehicle("A") == [a30]
    assert live.of_vehicle("C") == [moved]

    del live.units[a30.ref.key]
    assert live.of_vehicle("A") == []
    assert live.vehicle_ids() == {"B", "C"}
    assert live.units.pop(b30.ref.key) is b30
    assert live.units.pop(("nowhere", 1), None) is None
    assert live.vehicle_ids() == {"C"}
    live.units.clear()
    assert live.vehicle_ids() == set()
    assert live.of_vehicle("C") == []


def test_a_unit_never_heard_is_not_online_until_its_first_frame() -> None:
    """A unit known only from the configuration or another gateway's units row (no frame
    heard yet) is offline to the API, as it is to the command check, which refuses it; its
    first frame makes it online."""
    unit = _unit("A", "a/0", 30)
    assert (unit.is_online(), unit.state()) == (False, "offline")
    unit.last_seen = time.time()
    assert (unit.is_online(), unit.state()) == (True, "online")
