"""Fault episodes: DM1 and status flags, stale DM1, offline units, stuck heartbeat; event hub."""

from __future__ import annotations

import asyncio

import pytest

from eqgw.ingest import events
from eqgw.ingest.events import Event, UnitRef
from eqgw.ingest.faults import FaultTracker
from eqgw.ingest.hub import EventHub, SubscriberLagged
from tests.bus_helpers import within

OVF = {"spn": 168, "fmi": 0, "oc": 3, "cm": 0, "code": "OVF"}
UVF = {"spn": 168, "fmi": 1, "oc": 1, "cm": 0, "code": "UVF"}
LAMPS = {"mil": 0, "rsl": 0, "awl": 1, "pl": 0}


def dm1(*dtcs: dict[str, object]) -> dict[str, object]:
    return {"lamps": LAMPS, "dtcs": list(dtcs)}


def kinds(changes: list[tuple[str, object]]) -> list[str]:
    return [k for k, _ in changes]


def test_dm1_episode_opens_and_all_clear_closes() -> None:
    t = FaultTracker()
    assert kinds(t.on_dm1(10.0, dm1(OVF))) == [events.FAULT_OPEN]
    assert t.on_dm1(11.0, dm1(OVF)) == []
    ((kind, ep),) = t.on_dm1(12.0, dm1({**OVF, "oc": 4}))
    assert (kind, ep.occurrence_count) == (events.FAULT_UPDATE, 4)
    ((kind, ep),) = t.on_dm1(13.0, dm1())
    assert (kind, ep.state, ep.ended_at, ep.ended_by) == (
        events.FAULT_CLOSE,
        "closed",
        13.0,
        "dm1_all_clear",
    )
    assert t.open == {}
    assert t.episode_counts == {"OVF": 1}


def test_dm1_that_stops_makes_the_episode_stale_not_closed() -> None:
    t = FaultTracker(dm1_stale_after_s=5.0)
    t.on_dm1(10.0, dm1(OVF, UVF))
    assert t.tick(14.0) == []
    changes = t.tick(15.5)
    assert sorted(ep.fault for _, ep in changes) == ["OVF", "UVF"]
    assert set(kinds(changes)) == {events.FAULT_STALE}
    assert t.tick(30.0) == []  # reported once
    assert t.open["OVF"].state == "stale"
    # It comes back: same episode, active again; UVF is no longer listed: closed.
    changes = t.on_dm1(31.0, dm1(OVF))
    assert (events.FAULT_UPDATE, "OVF") in [(k, ep.fault) for k, ep in changes]
    assert (events.FAULT_CLOSE, "UVF") in [(k, ep.fault) for k, ep in changes]
    assert t.open["OVF"].state == "active"
    assert t.episode_counts == {"OVF": 1, "UVF": 1}


def test_status_flags_confirm_and_clear() -> None:
    t = FaultTracker(dm1_stale_after_s=5.0)
    t.on_dm1(10.0, dm1(OVF))
    t.on_status(10.5, {"ovf": "active"})
    assert t.open["OVF"].source == "dm1+status"
    # The DM1 stops but the flag is still active: not stale.
    assert t.tick(20.0) == []
    # The flag clears while the DM1 is silent: closed by the status flags.
    ((kind, ep),) = t.on_status(21.0, {"ovf": "inactive"})
    assert (kind, ep.ended_by) == (events.FAULT_CLOSE, "status")
    # "error" / "not_available" say nothing.
    t.on_status(30.0, {"uvf": "active"})
    assert t.on_status(31.0, {"uvf": "not_available"}) == []
    assert "UVF" in t.open


def test_flag_clear_while_dm1_repeats_keeps_the_episode() -> None:
    t = FaultTracker(dm1_stale_after_s=5.0)
    t.on_status(10.0, {"imb": "active"})
    t.on_dm1(10.5, dm1({"spn": 520448, "fmi": 0, "oc": 1, "cm": 0, "code": "IMB"}))
    assert t.on_status(11.0, {"imb": "inactive"}) == []
    ((kind, ep),) = t.on_dm1(12.0, dm1())
    assert (kind, ep.fault, ep.ended_by) == (events.FAULT_CLOSE, "IMB", "dm1_all_clear")


def test_offline_and_back() -> None:
    t = FaultTracker(offline_after_s=10.0)
    t.on_frame(100.0)
    assert t.tick(109.0) == []
    ((kind, ep),) = t.tick(110.5)
    assert (kind, ep.fault, ep.started_at) == (events.FAULT_OPEN, "OFFLINE", 100.0)
    assert t.tick(200.0) == []
    ((kind, ep),) = t.on_frame(201.0)
    assert (kind, ep.ended_at, ep.ended_by) == (events.FAULT_CLOSE, 201.0, "frame")


def test_stuck_heartbeat() -> None:
    t = FaultTracker(heartbeat_stuck_after=3)
    for i, hb in enumerate([0, 1, 2, 3, 0]):
        assert t.on_heartbeat(float(i), hb) == []
    assert t.on_heartbeat(5.0, 0) == []
    ((kind, ep),) = t.on_heartbeat(6.0, 0)
    assert (kind, ep.fault) == (events.FAULT_OPEN, "HEARTBEAT_STUCK")
    assert t.on_heartbeat(7.0, 0) == []
    ((kind, _),) = t.on_heartbeat(8.0, 1)
    assert kind == events.FAULT_CLOSE
    assert t.on_heartbeat(9.0, None) == []


def test_unknown_dtc_gets_an_spn_fmi_name() -> None:
    t = FaultTracker()
    ((_, ep),) = t.on_dm1(1.0, dm1({"spn": 1234, "fmi": 5, "oc": 1, "cm": 0, "code": None}))
    assert (ep.fault, ep.spn, ep.fmi) == ("SPN1234/FMI5", 1234, 5)


UNIT = UnitRef("V1", "V1/can0", 30)


async def test_hub_delivers_by_kind_and_predicate() -> None:
    hub = EventHub()
    assert not hub.wants(events.RECORD)
    faults = hub.subscribe([events.FAULT_OPEN, events.FAULT_CLOSE])
    v2 = hub.subscribe(predicate=lambda e: e.unit.vehicle_id == "V2")
    assert hub.wants(events.RECORD) and hub.subscribers == 2
    hub.publish(Event(events.RECORD, UNIT, 1.0, {"name": "voltages"}))
    hub.publish(Event(events.FAULT_OPEN, UNIT, 2.0, {"fault": "OVF"}))
    got = await within(faults.get(), 1)
    assert got.kind == events.FAULT_OPEN and got.to_dict()["unit"]["sa"] == 30
    assert v2.get_nowait() is None
    faults.close()
    assert hub.subscribers == 1
    with pytest.raises(StopAsyncIteration):
        await faults.get()
    with pytest.raises(ValueError):
        hub.subscribe(["nope"])
    hub.close()


async def test_slow_subscriber_is_dropped_not_waited_for() -> None:
    hub = EventHub()
    slow = hub.subscribe(maxsize=3)
    fast = hub.subscribe(maxsize=100)
    for i in range(10):
        hub.publish(Event(events.RECORD, UNIT, float(i)))
    assert slow.lagged and hub.subscribers == 1
    assert hub.stats.dropped_subscribers == 1
    received = []
    with pytest.raises(SubscriberLagged):
        while True:
            received.append(await within(slow.get(), 1))
    assert len(received) <= 3
    assert [e.ts for e in [fast.get_nowait() for _ in range(10)] if e] == [
        float(i) for i in range(10)
    ]


async def test_waiting_subscriber_wakes_on_close() -> None:
    hub = EventHub()
    sub = hub.subscribe()

    async def consume() -> list[Event]:
        return [e async for e in sub]

    task = asyncio.create_task(consume())
    await asyncio.sleep(0)
    hub.publish(Event(events.LIVE, UNIT, 1.0))
    await asyncio.sleep(0)
    hub.close()
    assert [e.kind for e in await within(task, 1)] == [events.LIVE]
