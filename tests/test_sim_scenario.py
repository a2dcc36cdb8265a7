"""Scenario files, the shipped examples, the fleet API (naming, seeds, recording, runners)."""

from __future__ import annotations

import asyncio
import time
from pathlib import Path

import can
import pytest

from eqgw.protocol.decode import FrameDecoder
from eqgw.protocol.records import Record
from eqgw.sim.clock import ManualClock, RealtimeClock
from eqgw.sim.fleet import SimulatedFleet, generate_specs
from eqgw.sim.scenario import (
    ScenarioError,
    builtin_scenarios,
    load_scenario,
    parse_duration,
    parse_scenario,
)


def test_durations() -> None:
    assert parse_duration(90) == 90.0
    assert parse_duration("90s") == 90.0
    assert parse_duration("10m") == 600.0
    assert parse_duration("1h30m") == 5400.0
    for bad in ("soon", "-5", True, None):
        with pytest.raises(ScenarioError):
            parse_duration(bad)


def test_scenario_parsing_and_undo_events(tmp_path: Path) -> None:
    path = tmp_path / "s.yaml"
    path.write_text(
        """
seed: 5
vehicles:
  - name: BUS-1
    units: [{sa: 30, series: 70, rating: 60}, {sa: 31, series: 70, rating: 60}]
    soc: 0.7
events:
  - {at: 1m, vehicle: BUS-1, action: add_12v_load, amps: 50, for: 30s}
  - {at: 10, vehicle: all, action: fail_equalizer, sa: 31, for: 5}
  - {at: 0, vehicle: BUS-1, action: stop_heartbeat, mode: silent}
"""
    )
    sc = load_scenario(path)
    assert sc.seed == 5 and [v.name for v in sc.vehicles] == ["BUS-1"]
    assert [u.sa for u in sc.vehicles[0].units] == [30, 31]
    assert sc.vehicles[0].soc_a == sc.vehicles[0].soc_b == 0.7
    assert [(e.at, e.action) for e in sc.events] == [
        (0.0, "stop_heartbeat"),
        (10.0, "fail_equalizer"),
        (15.0, "restore_equalizer"),
        (60.0, "add_12v_load"),
        (90.0, "remove_12v_load"),
    ]
    add = sc.events[3]
    assert sc.events[4].args == {"name": add.args["name"]}  # removes that load only
    assert sc.events[2].args == {"sa": 31}


def test_toml_scenario(tmp_path: Path) -> None:
    path = tmp_path / "s.toml"
    path.write_text('[[events]]\nat = "5s"\nvehicle = "SIM-001"\naction = "alternator_off"\n')
    sc = load_scenario(path)
    assert sc.events[0].action == "alternator_off" and sc.vehicles == []


@pytest.mark.parametrize(
    "data, reason",
    [
        ({"events": [{"at": 1, "vehicle": "X", "action": "explode"}]}, "unknown action"),
        ({"events": [{"at": 1, "vehicle": "X", "action": "alternator_off", "x": 1}]}, "takes"),
        ({"events": [{"vehicle": "X", "action": "alternator_off"}]}, "at is required"),
        ({"events": [{"at": 1, "vehicle": "X", "action": "set_soc", "for": 3}]}, "no undo"),
        ({"vehicles": [{"name": "A"}, {"name": "A"}]}, "unique"),
        ({"vehicles": [{"name": "A", "units": [{"series": 90}]}]}, "series"),
        ({"vehicles": [{"name": "A", "colour": "red"}]}, "unknown keys"),
        ({"fleet": []}, "unknown top-level"),
    ],
)
def test_bad_scenarios_say_why(data: object, reason: str) -> None:
    with pytest.raises(ScenarioError, match=reason):
        parse_scenario(data)


def test_event_for_unknown_vehicle_is_refused() -> None:
    sc = parse_scenario({"events": [{"at": 1, "vehicle": "NOPE", "action": "alternator_off"}]})
    with pytest.raises(ValueError, match="NOPE"):
        SimulatedFleet(2, scenario=sc, clock=ManualClock())


def test_generated_fleet_names_and_mix() -> None:
    specs = generate_specs(20, seed=0)
    assert [s.name for s in specs][:3] == ["SIM-001", "SIM-002", "SIM-003"]
    assert specs[-1].name == "SIM-020"
    assert {u.series for s in specs for u in s.units} == {70, 80}
    assert any(len(s.units) == 2 for s in specs)
    assert all([u.sa for u in s.units] in ([30], [30, 31]) for s in specs)
    assert generate_specs(20, seed=0) == specs
    assert generate_specs(20, seed=1) != specs


def test_scenario_vehicles_come_first_then_generated_ones() -> None:
    sc = parse_scenario({"vehicles": [{"name": "COACH-9"}]})
    fleet = SimulatedFleet(3, scenario=sc, clock=ManualClock())
    assert fleet.names == ["COACH-9", "SIM-001", "SIM-002"]
    assert len(set(fleet.channels.values())) == 3


def frames_of(fleet: SimulatedFleet, seconds: float) -> list[tuple[str, float, int, bytes]]:
    out: list[tuple[str, float, int, bytes]] = []
    for name in fleet.names:
        fleet.add_tap(
            name, lambda m, n=name: out.append((n, m.timestamp, m.arbitration_id, bytes(m.data)))
        )
    fleet.advance(seconds)
    fleet.close()
    return sorted(out)


def test_same_seed_same_frames() -> None:
    a = frames_of(SimulatedFleet(4, seed=3, clock=ManualClock(), background_traffic=True), 30.0)
    b = frames_of(SimulatedFleet(4, seed=3, clock=ManualClock(), background_traffic=True), 30.0)
    c = frames_of(SimulatedFleet(4, seed=4, clock=ManualClock(), background_traffic=True), 30.0)
    assert a == b and a != c


def run_scenario(
    name: str, until_s: float, step_s: float = 5.0
) -> dict[tuple[str, int], list[Record]]:
    """Run a shipped scenario; DM1 records per (vehicle, sa), read off each bus."""
    fleet = SimulatedFleet(scenario=builtin_scenarios()[name], clock=ManualClock())
    readers = {n: can.Bus(interface="virtual", channel=c) for n, c in fleet.channels.items()}
    decoder = FrameDecoder(equalizer_sas=(30, 31), only=("dm1",))
    out: dict[tuple[str, int], list[Record]] = {}
    try:
        fleet.open()
        while fleet.elapsed < until_s:
            fleet.advance(step_s)
            for n, bus in readers.items():
                while (m := bus.recv(timeout=0)) is not None:
                    m.channel = n
                    for r in decoder.decode_message(m):
                        out.setdefault((n, r.sa), []).append(r)
    finally:
        for bus in readers.values():
            bus.shutdown()
        fleet.close()
    return out


def codes_seen(records: list[Record]) -> set[str]:
    return {d["code"] for r in records for d in r.fields["dtcs"]}


def test_builtin_scenarios_are_shipped() -> None:
    assert {"night-undervoltage", "overload-imbalance", "equalizer-fault"} <= set(
        builtin_scenarios()
    )


def test_night_of_undervoltage() -> None:
    dm1 = run_scenario("night-undervoltage", 5 * 3600, step_s=10.0)
    assert "UVF" in codes_seen(dm1[("NIGHT-01", 30)])
    assert ("NIGHT-02", 30) not in dm1  # the lightly loaded coach gets through the night


def test_overload_imbalance_raises_and_clears_imb() -> None:
    dm1 = run_scenario("overload-imbalance", 25 * 60)
    records = dm1[("OVERLOAD-01", 30)]
    assert codes_seen(records) == {"IMB"}
    assert records[-1].fields["dtcs"] == []  # the all-clear once the load is gone


def test_equalizer_fault_scenario() -> None:
    dm1 = run_scenario("equalizer-fault", 20 * 60)
    assert {"EQFLT", "IMB"} <= codes_seen(dm1[("EQFAULT-01", 30)])
    assert codes_seen(dm1[("EQFAULT-02", 31)]) == {"EQFLT"}
    assert ("EQFAULT-02", 30) not in dm1  # the healthy unit of the pair keeps balancing
    for key in (("EQFAULT-01", 30), ("EQFAULT-02", 31)):
        assert dm1[key][-1].fields["dtcs"] == []  # repaired: all-clear


def test_record_writes_candump_logs(tmp_path: Path) -> None:
    fleet = SimulatedFleet(2, clock=ManualClock(1_700_000_000.0), record_dir=tmp_path)
    with fleet:
        sender = can.Bus(interface="virtual", channel=fleet.channels["SIM-001"])
        try:
            sender.send(can.Message(arbitration_id=0x18EA1ED8, data=b"\xeb\xfe\x00"))
            fleet.advance(10.0)
        finally:
            sender.shutdown()
    logs = sorted(p.name for p in tmp_path.iterdir())
    assert logs == ["SIM-001.log", "SIM-002.log"]
    msgs = list(can.CanutilsLogReader(tmp_path / "SIM-001.log"))
    assert len(msgs) > 6
    assert all(m.channel == "SIM-001" for m in msgs)
    assert all(1_700_000_000.0 <= m.timestamp <= 1_700_000_010.0 for m in msgs)
    received = [m for m in msgs if m.arbitration_id == 0x18EA1ED8]
    assert len(received) == 1 and received[0].is_rx
    assert any(m.arbitration_id == 0x18FEEB1E for m in msgs)  # the answer is logged too


def wait_for(condition: object, timeout: float = 20.0) -> None:
    assert callable(condition)
    deadline = time.monotonic() + timeout
    while not condition():
        if time.monotonic() > deadline:
            raise AssertionError("condition not met in time")
        time.sleep(0.02)


def test_thread_runner_in_real_time() -> None:
    fleet = SimulatedFleet(2, clock=RealtimeClock(speed=20.0), tick_s=0.01)
    reader = can.Bus(interface="virtual", channel=fleet.channels["SIM-002"])
    seen: list[can.Message] = []
    try:
        fleet.start_thread()

        def enough() -> bool:
            while (m := reader.recv(timeout=0)) is not None:
                seen.append(m)
            return sum(1 for m in seen if m.arbitration_id == 0x18FFD41E) >= 3

        wait_for(enough)
        fleet.alternator_off("SIM-002")  # injection while the thread runs
        assert fleet.error is None
    finally:
        fleet.close()
        reader.shutdown()
    assert fleet._thread is None


async def test_async_runner_in_real_time() -> None:
    fleet = SimulatedFleet(1, clock=RealtimeClock(speed=20.0), tick_s=0.01)
    reader = can.Bus(interface="virtual", channel=fleet.channels["SIM-001"])
    try:
        async with fleet:
            deadline = time.monotonic() + 20.0
            count = 0
            while count < 3 and time.monotonic() < deadline:
                while (m := reader.recv(timeout=0)) is not None:
                    count += m.arbitration_id == 0x18FFD51E
                await asyncio.sleep(0.02)
            assert count >= 3
            assert fleet.elapsed > 5.0
    finally:
        reader.shutdown()


def test_stepped_clock_refuses_thread() -> None:
    fleet = SimulatedFleet(1, clock=ManualClock())
    with pytest.raises(TypeError):
        fleet.start_thread()
    fleet.close()
