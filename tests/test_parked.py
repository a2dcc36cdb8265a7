"""Parked vehicles: a unit silent with its whole bus (ignition off) is parked, not offline;
a unit silent while its bus carries traffic is offline; a vehicle not heard for
`monitor.not_reporting_after_s` is not reporting (one alert per vehicle).

The monitor on its own (pure), then the simulator's `ignition-off` scenario through the
pipeline and the alert engine on a manual clock (every node's frames, background traffic
included, as a gateway's bus reader hands them over)."""

from __future__ import annotations

import asyncio
import time
from typing import Any

import can
from sqlalchemy import Engine

from eqgw.config import Settings
from eqgw.ingest import events
from eqgw.ingest.faults import OFFLINE, BusActivity, FaultTracker
from eqgw.ingest.service import IngestService
from eqgw.ingest.state import vehicle_status
from eqgw.protocol.encode import encode
from tests.alerts_helpers import EPOCH, Rig
from tests.test_ingest_restart import OpeningSource, _feed, _until

# -- the monitor --------------------------------------------------------------------------


def _bus(*frames: float) -> BusActivity:
    bus = BusActivity(silent_after_s=6.0)
    for ts in frames:
        bus.on_frame(ts)
    return bus


def test_a_unit_silent_with_its_whole_bus_is_parked_not_offline() -> None:
    t = FaultTracker(offline_after_s=10.0)
    bus = _bus()
    for ts in range(0, 101):
        t.on_frame(float(ts))
        bus.on_frame(float(ts) + 0.3)  # the engine's frames, a little after the unit's
    # Ignition off: nothing on the bus after 100.3. Parked once the bus is silent for
    # bus_silent_after_s, before the offline window, and never offline however long.
    assert t.tick(105.0, bus) == [] and t.parked_since is None
    assert t.tick(107.0, bus) == []
    assert t.parked_since == 100.3
    for now in (111.0, 200.0, 36 * 3600.0):
        assert t.tick(now, bus) == []
    assert OFFLINE not in t.open
    # Ignition on: the bus carries traffic again and the unit is heard: no episode.
    bus.on_frame(50_000.0)
    assert t.tick(50_000.5, bus) == [] and t.parked_since == 100.3
    assert t.on_frame(50_001.0) == [] and t.parked_since is None
    assert t.tick(50_005.0, bus) == [] and t.open == {}


def test_a_unit_silent_while_its_bus_carries_traffic_is_offline() -> None:
    t = FaultTracker(offline_after_s=10.0)
    bus = _bus()
    t.on_frame(100.0)
    for i in range(1, 200):
        bus.on_frame(100.0 + i * 0.1)  # other nodes go on
        now = 100.0 + i * 0.1
        changes = t.tick(now, bus)
        if changes:
            ((kind, ep),) = changes
            assert (kind, ep.fault, ep.started_at) == (events.FAULT_OPEN, OFFLINE, 100.0)
            assert 110.0 < now <= 110.2
            break
    else:
        raise AssertionError("the unit never went offline")
    assert t.parked_since is None


def test_a_parked_unit_not_heard_after_its_bus_is_back_is_offline() -> None:
    t = FaultTracker(offline_after_s=10.0)
    bus = _bus(99.9)
    t.on_frame(100.0)
    t.tick(110.0, bus)
    assert t.parked_since == 100.0
    # The bus is back at 5000 (ignition on) without this unit: the offline window counts
    # from the bus's return, not from the unit's last frame the evening before.
    for i in range(0, 95):
        bus.on_frame(5000.0 + i * 0.1)
    assert t.tick(5009.4, bus) == [] and t.parked_since == 100.0
    for i in range(95, 110):
        bus.on_frame(5000.0 + i * 0.1)
    ((kind, ep),) = t.tick(5010.9, bus)
    assert (kind, ep.fault) == (events.FAULT_OPEN, OFFLINE)
    assert t.parked_since is None


# -- the ignition-off scenario through the pipeline and the alert engine --------------------


def _states(rig: Rig, now: float) -> dict[str, dict[str, Any]]:
    live = rig.pipeline.live
    after = rig.settings.monitor.not_reporting_after_s
    return {
        vid: vehicle_status(live.of_vehicle(vid), now, after).to_dict()
        for vid in sorted(live.vehicle_ids())
    }


async def test_the_ignition_off_scenario_pages_nobody_for_parked_coaches(engine: Engine) -> None:
    rig = Rig(engine, scenario="ignition-off")
    hub = rig.hub.subscribe(
        {events.FAULT_OPEN, events.UNIT_PARKED, events.UNIT_ONLINE, events.VEHICLE_STATE}
    )
    seen: dict[float, dict[str, dict[str, Any]]] = {}

    def look(now: float) -> None:
        if round(now - EPOCH) in (55, 150, 4 * 60):
            seen[round(now - EPOCH)] = _states(rig, now)

    await rig.start()
    try:
        await rig.run(4 * 60, step=1.0, each=look)
    finally:
        await rig.stop()
    # Before the evening: every coach reporting.
    assert {v: s["state"] for v, s in seen[55].items()} == {
        "EVENING-01": "ok",
        "EVENING-02": "ok",
        "LATE-03": "ok",
    }
    # Switched off at 1 min: parked since its bus's last frame, last heard then; LATE-03's
    # unit lost its wiring at 90 s while its partner talks on: offline.
    mid = seen[150]
    for vid in ("EVENING-01", "EVENING-02"):
        assert mid[vid]["state"] == "parked", mid
        assert 60 - 4 <= mid[vid]["parked_since"] - EPOCH <= 60
        assert 60 - 4 <= mid[vid]["last_heard"] - EPOCH <= 60
    assert mid["LATE-03"]["state"] == "offline" and mid["LATE-03"]["parked_since"] is None
    # Switched on at 3 min: everything reporting again.
    assert {v: s["state"] for v, s in seen[4 * 60].items()} == {
        "EVENING-01": "ok",
        "EVENING-02": "ok",
        "LATE-03": "ok",
    }
    # One alert in the whole evening: the unit that lost its wiring, cleared once heard.
    alerts = rig.alerts()
    assert [(a["vehicle_id"], a["sa"], a["rule"]) for a in alerts] == [("LATE-03", 31, "offline")]
    (a,) = alerts
    assert 90 + 10 <= a["raised_at"] - EPOCH <= 90 + 12
    assert a["state"] == "cleared" and 150 <= a["cleared_at"] - EPOCH <= 155
    got: list[Any] = []
    while not hub.queue.empty():
        got.append(hub.queue.get_nowait())
    # No OFFLINE episode for a parked unit; each parked unit said so once and came back once.
    opened = [(e.unit.vehicle_id, e.unit.sa) for e in got if e.kind == events.FAULT_OPEN]
    assert ("LATE-03", 31) in opened
    assert not [o for o in opened if o[0].startswith("EVENING")]
    parked = sorted((e.unit.vehicle_id, e.unit.sa) for e in got if e.kind == events.UNIT_PARKED)
    assert parked == [("EVENING-01", 30), ("EVENING-02", 30), ("EVENING-02", 31)]
    back = sorted(
        (e.unit.vehicle_id, e.unit.sa)
        for e in got
        if e.kind == events.UNIT_ONLINE and "parked_since" in e.data
    )
    assert back == parked
    # The vehicle's state changes went out as events, on the vehicle's lowest unit.
    changes = [
        (e.unit.vehicle_id, e.unit.sa, e.data["state"])
        for e in got
        if e.kind == events.VEHICLE_STATE and e.unit.vehicle_id == "EVENING-02"
    ]
    assert changes[0] == ("EVENING-02", 30, "parked")
    assert changes[-1] == ("EVENING-02", 30, "ok")


async def test_a_vehicle_not_heard_for_long_raises_one_alert_cleared_when_heard(
    engine: Engine,
) -> None:
    # The generated fleet's third vehicle has two units: still one alert for it.
    rig = Rig(engine, 3, monitor={"not_reporting_after_s": 300.0}, background_traffic=True)
    await rig.start()
    try:
        await rig.run(20)
        t_off = rig.clock.now()
        rig.fleet.ignition_off("SIM-003")
        rig.fleet.ignition_off("SIM-001")
        await rig.run(6 * 60)
        mid = _states(rig, rig.clock.now())
        rig.fleet.ignition_on("SIM-003")
        rig.fleet.ignition_on("SIM-001")
        await rig.run(40)
    finally:
        await rig.stop()
    assert len(rig.pipeline.live.of_vehicle("SIM-003")) == 2
    alerts = rig.alerts()
    assert sorted((a["vehicle_id"], a["rule"]) for a in alerts) == [
        ("SIM-001", "not_reporting"),
        ("SIM-003", "not_reporting"),
    ]
    for a in alerts:
        assert a["sa"] == min(u.ref.sa for u in rig.pipeline.live.of_vehicle(a["vehicle_id"]))
        # Raised 300 s after the vehicle was last heard (within a step), cleared once heard.
        assert t_off - 4 + 300 <= a["raised_at"] <= t_off + 300 + 2
        assert a["values"]["last_heard"] <= t_off and "last heard" in a["message"]
        assert a["state"] == "cleared" and a["cleared_at"] > t_off + 6 * 60
    # Not heard for over 300 s while parked: not reporting outranks parked.
    assert mid["SIM-001"]["state"] == "not_reporting" and mid["SIM-002"]["state"] == "ok"


# -- a restart while the fleet is parked ----------------------------------------------------


async def test_a_gateway_restarted_while_the_fleet_is_parked_shows_it_parked(db_url: str) -> None:
    """The gateway restarts at night: every bus opens and carries nothing. The units restored
    from the database are parked once their bus has been silent, not shown online with the
    evening's values, and nothing is paged."""
    settings = Settings(
        database_url=db_url,
        buses=[{"name": "P/can0", "vehicle_id": "P", "interface": "virtual", "channel": "P"}],
        vehicles=[{"id": "P"}],
        monitor={"offline_after_s": 1.0, "bus_silent_after_s": 0.5, "dm1_stale_after_s": 3600},
    )
    fields = {"v12": 12.5, "v24": 25.0, "i12": 1.0, "i24": 2.0}
    src = OpeningSource("P/can0")
    src.state = "open"
    svc = IngestService(settings, sources=[src], retention=False)
    await svc.start()
    try:
        frames = [
            can.Message(timestamp=time.time(), arbitration_id=can_id, data=data, channel="P/can0")
            for can_id, data in encode("voltages", fields, sa=30)
        ]
        await _feed(svc, src, frames)
    finally:
        assert await svc.stop() == 0

    src = OpeningSource("P/can0")
    src.state = "open"
    svc = IngestService(settings, sources=[src], retention=False)
    opened = svc.hub.subscribe({events.FAULT_OPEN})
    await svc.start()
    try:
        (st,) = svc.live.of_vehicle("P")
        await _until(lambda: st.state() == "parked", "the restored unit parked")
        assert st.parked_since == st.last_seen
        await asyncio.sleep(0.5)
        assert opened.queue.empty() and "OFFLINE" not in st.faults.open
    finally:
        assert await svc.stop() == 0
