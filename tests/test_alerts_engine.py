"""The alert engine against the simulator's scenarios, bursts, two gateways, restart and lag."""

from __future__ import annotations

import asyncio
import sqlite3
import threading
from typing import Any

import pytest
from sqlalchemy import Engine

from eqgw.alerts import repository as aq
from eqgw.alerts.engine import AlertEngine
from eqgw.ingest import events
from eqgw.ingest.events import Event
from eqgw.supervisor import Supervisor
from tests.alerts_helpers import EPOCH, Rig

PAYLOAD_ALERT_KEYS = {
    "id", "vehicle_id", "vehicle_name", "bus", "sa", "rule", "severity", "state", "message",
    "values", "raised_at", "acknowledged_at", "acknowledged_by", "ack_comment", "cleared_at",
}  # fmt: skip


def _one(alerts: list[dict[str, Any]], **match: Any) -> dict[str, Any]:
    found = [a for a in alerts if all(a[k] == v for k, v in match.items())]
    assert len(found) == 1, (match, alerts)
    return found[0]


def _check_events(rig: Rig, alert: dict[str, Any], kinds: list[str]) -> None:
    evs = [e for e in rig.events() if e["alert_id"] == alert["id"]]
    assert [e["kind"] for e in evs] == kinds
    for e in evs:
        p = e["payload"]
        assert p["event"] == e["kind"] and p["ts"] == e["ts"]
        assert PAYLOAD_ALERT_KEYS <= set(p["alert"])
        assert p["alert"]["id"] == alert["id"] and p["alert"]["rule"] == alert["rule"]
        assert e["muted"] is False


async def test_equalizer_fault_scenario(engine: Engine) -> None:
    rig = Rig(engine, scenario="equalizer-fault")
    await rig.start()
    try:
        await rig.run(20 * 60, step=1.0)
    finally:
        await rig.stop()
    faults = rig.alerts("equalizer_fault")
    # The failed 70-series unit and the failed half of the pair; the healthy unit never.
    assert {(a["vehicle_id"], a["sa"]) for a in faults} == {("EQFAULT-01", 30), ("EQFAULT-02", 31)}
    for a in faults:
        # Failed at 60 s; the unit reports EQFLT after its 10 s fault timer; no delay.
        assert 60 <= a["raised_at"] - EPOCH <= 75
        assert a["severity"] == "critical" and a["state"] == "cleared"
        # Repaired at 60 s + 15 min: cleared when the unit's all-clear arrives.
        assert 960 <= a["cleared_at"] - EPOCH <= 980
        assert a["cleared_by"] == "condition"
        assert a["values"] == {"fault": "EQFLT"}
        _check_events(rig, a, ["raised", "cleared"])
    payload = rig.events()[0]["payload"]["alert"]
    assert payload["vehicle_name"].endswith(" coach")


async def test_overload_imbalance_scenario(engine: Engine) -> None:
    rig = Rig(engine, scenario="overload-imbalance")
    await rig.start()
    seen: list[float] = []

    def watch(now: float) -> None:
        # When B - A first went beyond 0.10 V (the rule's firing level) or IMB was reported.
        st = rig.pipeline.live.get("OVERLOAD-01", 30)
        if st is None or seen or "voltages" not in st.latest:
            return
        f = st.latest["voltages"][1]
        if abs(f["v24"] - 2 * f["v12"]) > 0.10 or "IMB" in st.faults.open:
            seen.append(now)

    try:
        await rig.run(30 * 60, step=1.0, each=watch)
    finally:
        await rig.stop()
    a = _one(rig.alerts(), rule="imbalance")
    assert a["vehicle_id"] == "OVERLOAD-01"
    # Raised once the imbalance has held for the rule's 30 s delay (steps are 1 s).
    assert seen and seen[0] + 30 - 1 <= a["raised_at"] <= seen[0] + 30 + 2
    assert a["values"]["imbalance_v"] > 0.10
    assert set(a["values"]) == {"imbalance_v", "battery_a_v", "battery_b_v", "v12", "v24"}
    # The 100 A load goes at 30 s + 20 min; cleared once B - A is back under 0.07 V.
    assert a["state"] == "cleared" and a["cleared_at"] - EPOCH > 30 + 20 * 60
    _check_events(rig, a, ["raised", "cleared"])


async def test_night_undervoltage_scenario(sqlite_engine: Engine) -> None:
    rig = Rig(sqlite_engine, scenario="night-undervoltage")
    await rig.start()
    first_low: list[float] = []

    def watch(now: float) -> None:
        st = rig.pipeline.live.get("NIGHT-01", 30)
        if st is None or first_low:
            return
        v24 = st.latest.get("voltages", (0, {}))[1].get("v24")
        if (v24 is not None and v24 < 24.0) or "UVF" in st.faults.open:
            first_low.append(now)

    try:
        await rig.run(11 * 3600, step=10.0, each=watch)
    finally:
        await rig.stop()
    alerts = rig.alerts()
    a = _one(alerts, rule="undervoltage")
    assert a["vehicle_id"] == "NIGHT-01" and a["severity"] == "warning"
    assert first_low and first_low[0] <= a["raised_at"] <= first_low[0] + 10 + 10
    assert a["raised_at"] - EPOCH > 3 * 3600  # hours into the night, not at once
    # The engines start at 10 h: the alert clears in the morning, once.
    assert a["state"] == "cleared" and 10 * 3600 < a["cleared_at"] - EPOCH < 10.5 * 3600
    assert not [x for x in alerts if x["vehicle_id"] == "NIGHT-02"]  # the light coach is fine
    risk = _one(alerts, rule="shutdown_risk")
    assert risk["raised_at"] > a["raised_at"] and risk["state"] == "cleared"
    _check_events(rig, a, ["raised", "cleared"])


async def test_offline_by_cutting_a_units_wiring_while_the_bus_carries_traffic(
    engine: Engine,
) -> None:
    # The engine's and transmission's frames go on (other nodes' traffic counts): the silent
    # unit is offline, not parked.
    rig = Rig(engine, 1, background_traffic=True)
    await rig.start()
    try:
        await rig.run(30)
        assert rig.alerts() == []
        rig.fleet.disconnect_unit("SIM-001")
        t_off = rig.clock.now()
        await rig.run(30)
        a = _one(rig.alerts(), rule="offline")
        # OFFLINE after 10 s without a frame (monitor.offline_after_s), raised within a step.
        assert t_off <= a["raised_at"] <= t_off + 10 + 1
        rig.fleet.reconnect_unit("SIM-001")
        await rig.run(10)
    finally:
        await rig.stop()
    a = _one(rig.alerts(), rule="offline")
    assert a["state"] == "cleared"
    assert len(rig.alerts()) == 1


async def test_a_vehicle_whose_whole_bus_falls_silent_is_parked_not_paged(engine: Engine) -> None:
    # The wiring to the whole bus cut, or the ignition off: nothing is heard from any node.
    rig = Rig(engine, 1, background_traffic=True)
    await rig.start()
    try:
        await rig.run(30)
        rig.fleet.disconnect_bus("SIM-001")
        await rig.run(60)
        (st,) = rig.pipeline.live.of_vehicle("SIM-001")
        assert st.state() == "parked" and "OFFLINE" not in st.faults.open
        rig.fleet.reconnect_bus("SIM-001")
        await rig.run(10)
        assert st.state() == "online"
    finally:
        await rig.stop()
    assert rig.alerts() == []


async def test_a_burst_for_one_unit_raises_one_alert(engine: Engine) -> None:
    rig = Rig(engine, 1, alerts={"rules": {"equalizer_fault": {"params": {"delay_s": 0}}}})
    await rig.start()
    try:
        await rig.run(10)
        rig.fleet.fail_equalizer("SIM-001")
        st = rig.pipeline.live.get("SIM-001", 30)
        assert st is not None
        await rig.run(15)
        assert "EQFLT" in st.faults.open
        # A burst of events for the unit, handled by concurrent tasks: still one alert.
        for i in range(500):
            rig.hub.publish(Event(events.FAULT_UPDATE, st.ref, rig.clock.now() + i * 1e-3, {}))
        await asyncio.gather(*(rig.engine.drain() for _ in range(5)))
        await asyncio.gather(*(rig.engine.evaluate_all(rig.clock.now()) for _ in range(5)))
        assert len(rig.alerts("equalizer_fault")) == 1
    finally:
        await rig.stop()
    assert len([e for e in rig.events() if e["kind"] == "raised"]) == 1


async def test_two_gateways_on_one_database_raise_one_alert(engine: Engine) -> None:
    rig = Rig(engine, 1)
    await rig.start()
    other = AlertEngine(engine, rig.hub, rig.pipeline.live, rig.settings, clock=rig.clock.now)
    await other.start(run=False)
    try:
        await rig.run(10)
        rig.fleet.fail_equalizer("SIM-001")
        await rig.run(15)
        await asyncio.gather(
            rig.engine.evaluate_all(rig.clock.now()), other.evaluate_all(rig.clock.now())
        )
        a = _one(rig.alerts(), rule="equalizer_fault")
        assert rig.engine.states[("SIM-001", 30)]["equalizer_fault"].alert_id == a["id"]
        assert other.states[("SIM-001", 30)]["equalizer_fault"].alert_id == a["id"]
    finally:
        await other.stop()
        await rig.stop()


def test_the_database_allows_one_open_alert_per_unit_and_rule(engine: Engine) -> None:
    """Concurrent raisers (threads, own connections) get one alert; after it clears, a new
    one can open."""
    results: list[tuple[int, bool]] = []
    errors: list[BaseException] = []
    barrier = threading.Barrier(8)

    def raise_one() -> None:
        try:
            barrier.wait()
            with engine.begin() as conn:
                alert, created = aq.raise_alert(
                    conn, vehicle_id="V", bus="V/can0", sa=30, rule="imbalance",
                    severity="warning", message="m", values={}, ts=1.0, muted=False,
                )  # fmt: skip
            results.append((alert["id"], created))
        except BaseException as exc:
            errors.append(exc)

    threads = [threading.Thread(target=raise_one) for _ in range(8)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not errors, errors
    assert len({r[0] for r in results}) == 1
    assert sum(created for _, created in results) == 1
    with engine.begin() as conn:
        alert_id = results[0][0]
        assert aq.clear_alert(conn, alert_id, ts=2.0, by="condition") is not None
        assert aq.clear_alert(conn, alert_id, ts=3.0, by="condition") is None
        again, created = aq.raise_alert(
            conn, vehicle_id="V", bus="V/can0", sa=30, rule="imbalance", severity="warning",
            message="m", values={}, ts=4.0, muted=False,
        )  # fmt: skip
        assert created and again["id"] != alert_id
        assert [e["kind"] for e in aq.events_after(conn, 0)] == ["raised", "cleared", "raised"]
    with pytest.raises(Exception, match=r"(?i)unique|duplicate"), engine.begin() as conn:
        conn.execute(
            aq._alerts.insert().values(
                vehicle_id="V", bus="V/can0", sa=30, rule="imbalance", severity="warning",
                state="active", muted=False, message="m", values={}, raised_at=5.0,
                updated_at=5.0,
            )
        )  # fmt: skip


async def test_restart_takes_open_alerts_back(engine: Engine) -> None:
    rig = Rig(engine, 1)
    await rig.start()
    try:
        await rig.run(10)
        rig.fleet.fail_equalizer("SIM-001")
        await rig.run(15)
        a = _one(rig.alerts(), rule="equalizer_fault")
        # A restarted engine (same live state, as IngestService restores it) on the same rows.
        await rig.engine.stop()
        rig.engine = AlertEngine(
            engine, rig.hub, rig.pipeline.live, rig.settings, clock=rig.clock.now
        )
        await rig.engine.start(run=False)
        assert rig.engine.states[("SIM-001", 30)]["equalizer_fault"].alert_id == a["id"]
        await rig.run(10)
        assert len(rig.alerts("equalizer_fault")) == 1
        rig.fleet.restore_equalizer("SIM-001")
        await rig.run(15)
    finally:
        await rig.stop()
    a = _one(rig.alerts(), rule="equalizer_fault")
    assert a["state"] == "cleared"
    assert [e["kind"] for e in rig.events()] == ["raised", "cleared"]


async def test_dropped_by_the_hub_resyncs_from_live_state(engine: Engine) -> None:
    rig = Rig(engine, 1, hub_queue=3)
    await rig.start()
    try:
        await rig.run(10)
        rig.fleet.fail_equalizer("SIM-001")
        await rig.run(15)
    finally:
        await rig.stop()
    assert rig.engine.stats.resyncs >= 1
    assert _one(rig.alerts(), rule="equalizer_fault")["state"] == "active"


async def test_a_muted_alert_is_recorded_and_marked(engine: Engine) -> None:
    rig = Rig(engine, 2)
    with engine.begin() as conn:
        aq.insert_mute(
            conn,
            {"vehicle_id": "SIM-001", "rule": None, "starts_at": 0.0, "ends_at": 4e9},
            1.0,
        )
    await rig.start()
    try:
        await rig.run(10)
        rig.fleet.fail_equalizer("SIM-001")
        rig.fleet.fail_equalizer("SIM-002")
        await rig.run(15)
    finally:
        await rig.stop()
    muted = _one(rig.alerts(), rule="equalizer_fault", vehicle_id="SIM-001")
    loud = _one(rig.alerts(), rule="equalizer_fault", vehicle_id="SIM-002")
    assert muted["muted"] and not loud["muted"]
    by_alert = {e["alert_id"]: e for e in rig.events()}
    assert by_alert[muted["id"]]["muted"] and by_alert[muted["id"]]["payload"]["alert"]["muted"]
    assert not by_alert[loud["id"]]["muted"]


@pytest.fixture
def sqlite_engine(sqlite_url: str) -> Any:
    from eqgw.store.engine import create_engine
    from eqgw.store.migrate import upgrade_engine

    eng = create_engine(sqlite_url)
    upgrade_engine(eng)
    yield eng
    eng.dispose()


@pytest.mark.parametrize(
    "failure",
    [
        pytest.param(sqlite3.OperationalError("database is locked"), id="heals"),
        pytest.param(TypeError("raise_alert() got an unexpected keyword"), id="bug"),
    ],
)
async def test_a_failed_raise_is_retried_only_when_it_may_heal(
    sqlite_engine: Engine, monkeypatch: pytest.MonkeyPatch, failure: Exception
) -> None:
    # The database away (locked): counted, reported, the next evaluation raises it. A bug
    # (the same call fails the same way every time): the engine's loops stop, reported
    # failed by their supervisor, instead of failing at every evaluation forever.
    rig = Rig(sqlite_engine, 1, background_traffic=True, alerts={"tick_s": 0.05})
    supervisor = Supervisor()
    rig.engine.supervisor = supervisor
    real = aq.raise_alert
    calls = 0

    def raise_alert(*args: Any, **kw: Any) -> Any:
        nonlocal calls
        calls += 1
        if calls == 1 or isinstance(failure, TypeError):  # a bug fails every time
            raise failure
        return real(*args, **kw)

    monkeypatch.setattr(aq, "raise_alert", raise_alert)
    await rig.engine.start(run=True)
    rig.fleet.open()

    async def step() -> None:
        now = rig.fleet.advance(1.0)
        frames, rig._frames = rig._frames, []
        rig.pipeline.process_many(frames)
        rig.pipeline.tick(now)
        rig.pipeline.take_rows()
        await asyncio.sleep(0.1)  # the engine's own loops evaluate

    try:
        for _ in range(5):
            await step()
        rig.fleet.disconnect_unit("SIM-001")  # offline after 10 s of the bus's traffic
        loops = [supervisor.get("alert engine"), supervisor.get("alert tick")]

        def stopped() -> bool:
            return all(t is not None and t.state == "failed" for t in loops)

        async with asyncio.timeout(60):
            while not (rig.alerts() if isinstance(failure, sqlite3.Error) else stopped()):
                await step()
        if isinstance(failure, TypeError):
            # Each loop met the bug once and stopped, said so; nothing raised.
            for t in loops:
                assert t is not None and "TypeError" in (t.last_error or "")
            assert not rig.engine.running and calls == 2 and rig.alerts() == []
            assert rig.engine.stats.db_failures == 2
        else:
            assert [t.state for t in loops if t is not None] == ["running", "running"]
            assert rig.engine.running and calls == 2 and len(rig.alerts()) == 1
            assert rig.engine.stats.db_failures == 1
    finally:
        await rig.stop()
        await supervisor.stop()
