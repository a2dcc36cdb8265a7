"""The electrical model against the Theory of Operation and the troubleshooting table, read the
way a technician (or the gateway) would: battery A = V12, battery B = V24 - V12, from the
decoded voltages frames of a ManualClock fleet."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from typing import Any

import can
import pytest

from eqgw.protocol.decode import FrameDecoder
from eqgw.protocol.encode import encode
from eqgw.protocol.records import Record
from eqgw.sim.clock import ManualClock
from eqgw.sim.equalizer import EqualizerSpec
from eqgw.sim.fleet import SimulatedFleet
from eqgw.sim.model import Battery, ElectricalSystem, Stage, classify, ocv
from eqgw.sim.vehicle import VehicleSpec


class Reader:
    """Decodes what the simulated units send on one vehicle bus."""

    def __init__(self, channel: str, sas: tuple[int, ...]) -> None:
        self.bus = can.Bus(interface="virtual", channel=channel)
        self.decoder = FrameDecoder(equalizer_sas=sas)
        self.records: list[Record] = []

    def latest(self, name: str, sa: int = 30) -> dict[str, Any]:
        while (msg := self.bus.recv(timeout=0)) is not None:
            self.records.extend(self.decoder.decode_message(msg))
        return [r for r in self.records if r.name == name and r.sa == sa][-1].fields

    def send(self, name: str, fields: dict[str, Any]) -> None:
        for can_id, data in encode(name, fields, sa=0xD8):
            self.bus.send(can.Message(arbitration_id=can_id, data=data, is_extended_id=True))


Make = Callable[..., tuple[SimulatedFleet, Reader]]


@pytest.fixture
def make() -> Iterator[Make]:
    opened: list[tuple[SimulatedFleet, Reader]] = []

    def _make(
        rating: int = 100, sas: tuple[int, ...] = (30,), series: int = 80, **kwargs: Any
    ) -> tuple[SimulatedFleet, Reader]:
        kwargs.setdefault("alternator_on", False)
        kwargs.setdefault("load_12v_a", 0.0)
        kwargs.setdefault("load_24v_a", 0.0)
        units = [EqualizerSpec(sa=sa, series=series, rating_a=rating) for sa in sas]
        spec = VehicleSpec(name="V", units=units, **kwargs)
        fleet = SimulatedFleet([spec], clock=ManualClock(0.0))
        reader = Reader(fleet.channels["V"], sas)
        opened.append((fleet, reader))
        fleet.open()
        return fleet, reader

    yield _make
    for fleet, reader in opened:
        reader.bus.shutdown()
        fleet.close()


def reading(
    fleet: SimulatedFleet, reader: Reader, sa: int = 30
) -> tuple[float, str, dict[str, Any]]:
    """(B - A in volts, eqrn, status) from the next full broadcast cycle."""
    fleet.advance(3.0)
    v = reader.latest("voltages", sa)
    return v["v24"] - 2 * v["v12"], reader.latest("status", sa)["eqrn"], reader.latest("status", sa)


def test_standby_within_005_and_not_running(make: Make) -> None:
    fleet, reader = make(load_24v_a=10.0)  # scenario 1: 24 V load only
    diff, eqrn, status = reading(fleet, reader)
    assert abs(diff) <= 0.05 and eqrn == "inactive"
    assert fleet.vehicle("V").condition() == "standby"
    assert status["io_in_sdn"] == "inactive"


def test_normal_between_005_and_010_and_running(make: Make) -> None:
    fleet, reader = make(rating=100, load_12v_a=60.0, load_24v_a=5.0)
    diff, eqrn, _ = reading(fleet, reader)
    assert 0.05 < diff <= 0.10 + 0.005 and eqrn == "active"
    assert fleet.vehicle("V").condition() == "normal"


def test_full_rated_load_stays_within_010(make: Make) -> None:
    # The equalizer supplies the whole 12 V load, drawing half of it from each battery.
    fleet, reader = make(rating=80, load_12v_a=80.0)
    diff, eqrn, _ = reading(fleet, reader)
    assert eqrn == "active" and 0.05 < diff <= 0.10 + 0.005
    assert fleet.vehicle("V").unit().stage.amps > 0.75 * 80.0
    v = reader.latest("voltages")
    # Both batteries discharge; A a little faster, by what the 0.05..0.10 V band allows.
    assert v["i12"] < 0 and v["i24"] < 0
    assert abs(v["i24"]) <= abs(v["i12"]) <= 1.5 * abs(v["i24"])


def test_overload_above_010_running_at_rating(make: Make) -> None:
    fleet, reader = make(rating=60, load_12v_a=150.0)
    diff, eqrn, _ = reading(fleet, reader)
    assert diff > 0.10 and eqrn == "active"
    unit = fleet.vehicle("V").unit()
    # Limited to its rating, folded back a little as A and B drift apart (Overload Condition).
    assert 0.9 * 60.0 <= unit.stage.amps <= 60.0
    assert fleet.vehicle("V").condition() == "overload"
    # Battery A supplies what the equalizer cannot and falls behind B.
    a0 = fleet.vehicle("V").system.a.soc
    b0 = fleet.vehicle("V").system.b.soc
    fleet.advance(600.0)
    a1, b1 = fleet.vehicle("V").system.a.soc, fleet.vehicle("V").system.b.soc
    assert a0 - a1 > b0 - b1
    diff2, _, _ = reading(fleet, reader)
    assert diff2 > diff


def test_not_functioning_above_010_and_not_running(make: Make) -> None:
    fleet, reader = make(load_12v_a=30.0)
    fleet.fail_equalizer("V")
    fleet.advance(120.0)
    diff, eqrn, status = reading(fleet, reader)
    assert diff > 0.10 and eqrn == "inactive"
    assert status["eqflt"] == "active"
    assert fleet.vehicle("V").condition() == "not_functioning"
    fleet.restore_equalizer("V")
    fleet.advance(30.0)
    diff, eqrn, status = reading(fleet, reader)
    assert 0.05 < diff <= 0.105 and eqrn == "active" and status["eqflt"] == "inactive"


def test_battery_a_above_b_is_abnormal(make: Make) -> None:
    fleet, reader = make(load_12v_a=5.0)
    fleet.fail_battery_b("V")
    diff, eqrn, _ = reading(fleet, reader)
    assert diff < -0.05 and eqrn == "inactive"  # it only moves charge from B to A
    assert fleet.vehicle("V").condition() == "abnormal"
    fleet.advance(15.0)
    assert reader.latest("status")["imb"] == "active"
    fleet.restore_battery_b("V")
    fleet.advance(15.0)
    assert reader.latest("status")["imb"] == "inactive"


def test_load_wired_across_b_is_abnormal(make: Make) -> None:
    fleet, reader = make()
    fleet.vehicle("V").add_load_on_b(40.0)
    fleet.advance(600.0)
    diff, _, _ = reading(fleet, reader)
    assert diff < -0.05


def test_alternator_charges_both_and_keeps_balance(make: Make) -> None:
    fleet, reader = make(load_12v_a=40.0, soc_a=0.6, soc_b=0.6)
    fleet.alternator_on("V")
    diff, eqrn, _ = reading(fleet, reader)
    v = reader.latest("voltages")
    assert v["v24"] == pytest.approx(28.2, abs=0.01)
    assert v["i12"] > 0 and v["i24"] > 0  # both batteries charging
    assert 0.05 < diff <= 0.105 and eqrn == "active"


def test_shutdown_below_16_v_system(make: Make) -> None:
    fleet, reader = make(soc_a=0.02, soc_b=0.02, load_12v_a=20.0)
    _, eqrn, status = reading(fleet, reader)
    v = reader.latest("voltages")
    assert v["v24"] < 16.0
    assert status["io_in_sdn"] == "active" and eqrn == "inactive"


def test_shutdown_below_8_v_on_battery_a_and_jump_start_override(make: Make) -> None:
    # The no-start story: a 12 V load drained A alone below 8 V; B still holds up.
    fleet, reader = make(soc_a=0.02, soc_b=0.6, load_12v_a=10.0)
    _, eqrn, status = reading(fleet, reader)
    v = reader.latest("voltages")
    assert v["v12"] < 8.0 and v["v24"] > 16.0
    assert status["io_in_sdn"] == "active" and eqrn == "inactive"
    reader.send("control", {"can_jso": "enable"})
    _, eqrn, status = reading(fleet, reader)
    assert status["state_can_jso"] == "active"
    assert status["io_in_sdn"] == "inactive" and eqrn == "active"
    fleet.advance(300.0)
    assert reader.latest("voltages")["v12"] > 8.0  # A recovers with the unit running


def test_jump_start_brings_a_dead_system_back(make: Make) -> None:
    fleet, reader = make(soc_a=0.01, soc_b=0.01)
    _, _eqrn, status = reading(fleet, reader)
    assert status["io_in_sdn"] == "active"
    fleet.jump_start("V")
    fleet.advance(180.0)  # "do not crank for two or three minutes"
    v = reader.latest("voltages")
    assert v["v12"] > 8.0 and v["v24"] - v["v12"] > 8.0
    assert reader.latest("status")["io_in_sdn"] == "inactive"


def test_parallel_units_share_the_load(make: Make) -> None:
    fleet, reader = make(rating=60, sas=(30, 31), load_12v_a=110.0)
    diff, _, _ = reading(fleet, reader)
    vehicle = fleet.vehicle("V")
    a, b = vehicle.unit(30), vehicle.unit(31)
    assert a.stage.amps == pytest.approx(b.stage.amps)
    assert a.stage.amps <= 60.0 + 1e-6
    assert diff <= 0.105  # two 60 A units carry a 110 A load
    for sa in (30, 31):
        assert reader.latest("status", sa)["eqrn"] == "active"
    fleet.fail_equalizer("V", sa=31)
    diff, _, _ = reading(fleet, reader)
    assert diff > 0.10  # one 60 A unit is now overloaded
    assert reader.latest("status", 31)["eqrn"] == "inactive"
    assert reader.latest("status", 30)["eqrn"] == "active"


def test_soc_follows_discharge_and_charge(make: Make) -> None:
    fleet, _reader = make(battery_ah=100.0, load_12v_a=20.0, load_24v_a=10.0, soc_a=0.8)
    vehicle = fleet.vehicle("V")
    fleet.advance(3600.0)
    # 10 A from the string plus 20 A at 12 V shared by the equalizer: ~20 Ah each.
    assert vehicle.system.a.soc == pytest.approx(0.6, abs=0.03)
    # Held within 0.05..0.10 V, which is a few percent of charge at rest.
    assert vehicle.system.b.soc == pytest.approx(vehicle.system.a.soc, abs=0.07)
    fleet.alternator_on("V")
    fleet.advance(3600.0)
    assert vehicle.system.a.soc > 0.75


def test_open_circuit_voltage_curve() -> None:
    assert ocv(1.0) == pytest.approx(12.75)
    assert ocv(0.5) == pytest.approx(12.2)
    assert ocv(0.0) < 8.0  # a dead battery
    assert all(ocv(s / 100) < ocv((s + 1) / 100) for s in range(100))


def test_classify_rows() -> None:
    system = ElectricalSystem(a=Battery(), b=Battery(), stages=[Stage(100.0)])
    sol = system.solve()
    assert classify(sol, running=False) == "standby"


def test_battery_states_report_each_battery_on_its_own(make: Make) -> None:
    """The 12 V battery states are battery A's, the 24 V battery states battery B's: two
    batteries that start apart are reported apart (not the weaker one twice)."""
    fleet, reader = make(battery_ah=100.0, soc_a=0.55, soc_b=0.85, soh_a=0.7, soh_b=0.95)
    fleet.advance(10.0)
    vehicle = fleet.vehicle("V")
    a, b = vehicle.system.a, vehicle.system.b
    by_index: dict[int, dict[str, Any]] = {}
    for r in reader.records + _drain(reader):
        if r.name == "battery_states":
            by_index[r.fields["index"]] = r.fields
    assert by_index[1]["soh"] == pytest.approx(100.0 * a.soh, abs=0.1)
    assert by_index[3]["soh"] == pytest.approx(100.0 * b.soh, abs=0.1)
    assert by_index[2]["soc"] == pytest.approx(100.0 * a.soc, abs=0.2)
    assert by_index[4]["soc"] == pytest.approx(100.0 * b.soc, abs=0.2)
    assert by_index[4]["soc"] - by_index[2]["soc"] > 20.0


def _drain(reader: Reader) -> list[Record]:
    out: list[Record] = []
    while (msg := reader.bus.recv(timeout=0)) is not None:
        out.extend(reader.decoder.decode_message(msg))
    return out
