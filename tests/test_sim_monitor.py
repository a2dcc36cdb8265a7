"""The simulated Smart Monitor against the manuals: rates, layouts, DM1 rules, requests, control
and parameters. Time is a ManualClock; frames are read from the vehicle's virtual bus and decoded
with FrameDecoder."""

from __future__ import annotations

import itertools
from collections.abc import Callable, Iterator
from typing import Any

import can
import pytest

from eqgw.protocol.decode import FrameDecoder
from eqgw.protocol.encode import encode
from eqgw.protocol.j1939 import (
    PGN_COMPONENT_ID,
    PGN_COMPONENT_ID_70_MISPRINT,
    PGN_DM1,
    PGN_SOFTWARE_ID,
    PGN_TP_CM,
    PGN_TP_DT,
    compose_id,
    parse_id,
)
from eqgw.protocol.records import Record
from eqgw.sim.clock import ManualClock
from eqgw.sim.equalizer import DEFAULTS_9, EqualizerSpec
from eqgw.sim.fleet import SimulatedFleet
from eqgw.sim.vehicle import VehicleSpec

GATEWAY_SA = 0xD8
T0 = 1_000.0


class Tap:
    """A test's own endpoint on a vehicle bus: sends commands, decodes what the unit sends."""

    def __init__(self, channel: str, sas: tuple[int, ...]) -> None:
        self.bus = can.Bus(interface="virtual", channel=channel, preserve_timestamps=True)
        self.decoder = FrameDecoder(equalizer_sas=sas)
        self.frames: list[can.Message] = []
        self.records: list[Record] = []

    def drain(self) -> list[Record]:
        while (msg := self.bus.recv(timeout=0)) is not None:
            self.frames.append(msg)
            self.records.extend(self.decoder.decode_message(msg))
        return self.records

    def of(self, name: str, sa: int | None = None, since: float = -1.0) -> list[Record]:
        self.drain()
        return [
            r
            for r in self.records
            if r.name == name and (sa is None or r.sa == sa) and r.ts >= since
        ]

    def send(self, name: str, fields: dict[str, Any], **kwargs: Any) -> None:
        for can_id, data in encode(name, fields, sa=GATEWAY_SA, **kwargs):
            self.bus.send(can.Message(arbitration_id=can_id, data=data, is_extended_id=True))

    def close(self) -> None:
        self.bus.shutdown()


def vehicle(
    name: str = "V1",
    series: int = 80,
    rating: int = 100,
    sas: tuple[int, ...] = (30,),
    **kwargs: Any,
) -> VehicleSpec:
    units = [EqualizerSpec(sa=sa, series=series, rating_a=rating) for sa in sas]
    return VehicleSpec(name=name, units=units, **kwargs)


Make = Callable[..., tuple[SimulatedFleet, Tap]]


@pytest.fixture
def make() -> Iterator[Make]:
    opened: list[tuple[SimulatedFleet, Tap]] = []

    def _make(spec: VehicleSpec | None = None, **fleet_kwargs: Any) -> tuple[SimulatedFleet, Tap]:
        spec = spec or vehicle()
        fleet = SimulatedFleet([spec], clock=ManualClock(T0), **fleet_kwargs)
        tap = Tap(fleet.channels[spec.name], tuple(u.sa for u in spec.units))
        opened.append((fleet, tap))
        fleet.open()
        return fleet, tap

    yield _make
    for fleet, tap in opened:
        tap.close()
        fleet.close()


def run(fleet: SimulatedFleet, seconds: float, step: float = 0.1) -> None:
    """Advance in small steps, as a live fleet's ticker would."""
    for _ in range(round(seconds / step)):
        fleet.advance(step)


def intervals(records: list[Record]) -> list[float]:
    return [round(b.ts - a.ts, 6) for a, b in itertools.pairwise(records)]


# --- broadcast rates and layouts -----------------------------------------------------------


def test_80_series_rates_and_layouts(make: Make) -> None:
    fleet, tap = make(vehicle(series=80))
    fleet.advance(60.0)
    for name in ("status", "heartbeat", "voltages"):
        recs = tap.of(name)
        assert len(recs) == 20, name
        assert set(intervals(recs)) == {3.0}, name
    beats = [r.fields["heartbeat"] for r in tap.of("heartbeat")]
    assert beats == [0, 1] * 10  # alternates 0b00 / 0b01
    states = tap.of("battery_states")
    for index in range(1, 6):
        recs = [r for r in states if r.fields["index"] == index]
        assert len(recs) == 12 and set(intervals(recs)) == {5.0}, index
    volts = tap.of("voltages")[-1].fields
    assert volts["i12"] is not None and volts["i24"] is not None
    status = tap.of("status")[-1].fields
    assert status["eq_battflt"] == "inactive" and status["can_ss_msg_on"] == "active"
    assert all(r.ts >= T0 for r in tap.records)


def test_70_series_layout_has_no_currents_and_no_battery_states(make: Make) -> None:
    fleet, tap = make(vehicle(series=70, rating=80))
    fleet.advance(30.0)
    assert tap.of("battery_states") == []
    volts = tap.of("voltages")
    assert len(volts) == 10
    assert volts[-1].fields["i12"] is None and volts[-1].fields["i24"] is None
    assert volts[-1].fields["v24"] > 20
    raw = [m for m in tap.frames if parse_id(m.arbitration_id).pgn == 0xFFD6][-1]
    assert bytes(raw.data[4:]) == b"\xff\xff\xff\xff"  # bytes 4-8 unused
    assert tap.of("status")[-1].fields["eq_battflt"] == "not_available"


def test_battery_states_follow_the_batteries(make: Make) -> None:
    fleet, tap = make(vehicle(alternator_on=False, load_12v_a=40.0, battery_ah=100.0, soc_a=0.8))
    fleet.advance(6.0)
    first = {r.fields["index"]: r.fields for r in tap.of("battery_states")}
    sim = fleet.vehicle("V1").system
    assert first[2]["soc"] == pytest.approx(100 * sim.a.soc, abs=0.2)
    assert first[2]["dod"] == pytest.approx(100 - first[2]["soc"], abs=0.2)
    assert first[4]["soc"] == pytest.approx(100 * sim.b.soc, abs=0.2)  # the 24 V battery: B
    assert 0 < first[1]["runtime_min"] < 32000  # discharging: a finite run time
    assert first[5]["major_12v"] == 2  # discharging
    run(fleet, 600.0, step=1.0)
    last = {r.fields["index"]: r.fields for r in tap.of("battery_states")[-5:]}
    assert last[2]["soc"] < first[2]["soc"] - 1.0
    assert last[1]["runtime_min"] < first[1]["runtime_min"]
    fleet.alternator_on("V1")
    fleet.advance(6.0)
    charging = {r.fields["index"]: r.fields for r in tap.of("battery_states")[-5:]}
    assert charging[5]["major_24v"] == 1  # charging
    assert charging[3]["runtime_min"] == pytest.approx(0xFAFF * 0.5)


# --- DM1 -----------------------------------------------------------------------------------


def dm1_codes(record: Record) -> list[str | None]:
    return [d["code"] for d in record.fields["dtcs"]]


def test_dm1_single_frame_repeats_then_one_all_clear(make: Make) -> None:
    fleet, tap = make(vehicle(alternator_on=False))
    fleet.advance(5.0)
    assert tap.of("dm1") == []  # not sent while nothing is active
    t_write = fleet.now()
    tap.send("parameters", {"index": 9, "uv_setpoint_v": 26.0, "fault_timer_s": 2})
    run(fleet, 6.0)
    dm1 = tap.of("dm1")
    assert 2.0 <= dm1[0].ts - t_write <= 2.2  # after the fault timer
    assert set(intervals(dm1)) == {1.0}  # every second while active
    assert all(dm1_codes(r) == ["UVF"] for r in dm1)
    assert dm1[0].fields["dtcs"][0]["oc"] == 1
    assert dm1[0].fields["lamps"]["awl"] == 2  # 0x08, as the manuals print it
    frames = [m for m in tap.frames if parse_id(m.arbitration_id).pgn == PGN_DM1]
    assert all(len(m.data) == 8 for m in frames)  # one DTC: single frame
    assert m_hex(frames[0])[:12] == "0800a8000101"  # manual's UVF frame, OC 1
    status = tap.of("status", since=dm1[0].ts)
    assert status and all(s.fields["uvf"] == "active" for s in status)
    assert all(s.fields["eq_battflt"] == "active" for s in status)

    tap.send("parameters", {"index": 9, "uv_setpoint_v": 20.0})
    run(fleet, 10.0)
    after = tap.of("dm1", since=dm1[-1].ts + 0.01)
    assert len(after) == 1 and after[0].fields["dtcs"] == []  # one all-clear
    clear_frame = [m for m in tap.frames if parse_id(m.arbitration_id).pgn == PGN_DM1][-1]
    assert bytes(clear_frame.data) == bytes.fromhex("00ff00000000ffff")
    assert tap.of("status")[-1].fields["uvf"] == "inactive"

    tap.send("parameters", {"index": 9, "uv_setpoint_v": 26.0})
    run(fleet, 3.0)
    again = tap.of("dm1", since=after[0].ts + 0.01)
    assert again and again[0].fields["dtcs"][0]["oc"] == 2  # a new occurrence


def m_hex(msg: can.Message) -> str:
    return bytes(msg.data).hex()


def test_dm1_bam_for_several_dtcs(make: Make) -> None:
    fleet, tap = make(vehicle(alternator_on=False, load_12v_a=0.0))
    fleet.fail_equalizer("V1")
    tap.send("parameters", {"index": 9, "uv_setpoint_v": 26.0, "fault_timer_s": 1})
    run(fleet, 4.0)
    dm1 = [r for r in tap.of("dm1") if len(r.fields["dtcs"]) > 1]
    assert dm1, tap.of("dm1")
    assert dm1_codes(dm1[-1]) == ["UVF", "EQFLT"]
    tp = [m for m in tap.frames if parse_id(m.arbitration_id).pgn in (PGN_TP_CM, PGN_TP_DT)]
    cm, dt1, dt2 = tp[-3:]
    assert cm.arbitration_id == 0x18ECFF1E and cm.data[0] == 0x20
    assert bytes(cm.data[5:8]) == bytes((0xCA, 0xFE, 0x00))
    assert dt1.arbitration_id == dt2.arbitration_id == 0x1CEBFF1E  # TP.DT at priority 7
    assert [dt1.data[0], dt2.data[0]] == [1, 2]
    assert dt1.timestamp - cm.timestamp == pytest.approx(0.05)
    assert dt2.timestamp - dt1.timestamp == pytest.approx(0.05)
    status = tap.of("status")[-1].fields
    assert status["eqflt"] == "active" and status["uvf"] == "active"
    assert status["eqrn"] == "inactive"


def test_dm1_at_most_one_change_per_dtc_per_second(make: Make) -> None:
    fleet, tap = make(vehicle(alternator_on=False))
    fleet.advance(1.0)
    tap.send("parameters", {"index": 9, "fault_timer_s": 0})
    fleet.advance(0.1)
    # An intermittent fault: the condition flips every 0.2 s for 4 s.
    for i in range(20):
        uv = 26.0 if i % 2 == 0 else 20.0
        tap.send("parameters", {"index": 9, "uv_setpoint_v": uv})
        fleet.advance(0.2)
    run(fleet, 3.0)
    dm1 = tap.of("dm1")
    states = [(r.ts, "UVF" in dm1_codes(r)) for r in dm1]
    changes = [
        ts for (ts, on), (_, before) in zip(states[1:], states, strict=False) if on != before
    ]
    changes.insert(0, states[0][0])
    assert len(changes) >= 3
    assert all(b - a >= 1.0 - 1e-6 for a, b in itertools.pairwise(changes))
    assert len(dm1) < 20  # far fewer messages than condition flips


def test_dm1_on_request_is_all_clear_when_nothing_is_active(make: Make) -> None:
    fleet, tap = make()
    fleet.advance(1.0)
    tap.send("request", {"requested_pgn": PGN_DM1, "da": 30})
    fleet.advance(0.1)
    dm1 = tap.of("dm1")
    assert len(dm1) == 1 and dm1[0].fields["dtcs"] == []
    assert dm1[0].fields["lamps"] == {"mil": 0, "rsl": 0, "awl": 0, "pl": 0}


# --- requests ------------------------------------------------------------------------------


def test_request_answers_by_destination(make: Make) -> None:
    fleet, tap = make(vehicle(sas=(30, 31), rating=60))
    fleet.advance(0.5)
    tap.send("request", {"requested_pgn": PGN_COMPONENT_ID, "da": 0xFF})
    fleet.advance(0.1)
    ids = tap.of("component_id")
    assert sorted(r.sa for r in ids) == [30, 31]
    assert {r.fields["text"] for r in ids} == {"EQ8001"}
    raw = next(m for m in tap.frames if parse_id(m.arbitration_id).pgn == PGN_COMPONENT_ID)
    assert bytes(raw.data) == b"*EQ8001*"

    tap.send("request", {"requested_pgn": PGN_SOFTWARE_ID, "da": 31})
    fleet.advance(0.1)
    sw = tap.of("software_id")
    assert [(r.sa, r.fields["text"]) for r in sw] == [(31, "EQ8001")]

    tap.send("request", {"requested_pgn": PGN_SOFTWARE_ID, "da": 0x40})  # someone else
    tap.send("request", {"requested_pgn": 0xFEE5, "da": 30})  # unsupported PGN
    fleet.advance(0.1)
    assert len(tap.of("software_id")) == 1
    answered = {parse_id(m.arbitration_id).pgn for m in tap.frames}
    assert 0xFEE5 not in answered


def test_70_series_identifies_as_eq70(make: Make) -> None:
    fleet, tap = make(vehicle(series=70, rating=60))
    fleet.advance(0.5)
    tap.send("request", {"requested_pgn": PGN_COMPONENT_ID, "da": 30})
    tap.send("request", {"requested_pgn": PGN_SOFTWARE_ID, "da": 30})
    # A gateway that follows the 70-series manual asks for 0xFEED.
    tap.send("request", {"requested_pgn": PGN_COMPONENT_ID_70_MISPRINT, "da": 30})
    fleet.advance(0.1)
    ids = tap.of("component_id")
    assert [(r.pgn, r.fields["text"], r.fields["series"]) for r in ids] == [
        (PGN_COMPONENT_ID, "EQ7001", 70),
        (PGN_COMPONENT_ID_70_MISPRINT, "EQ7001", 70),
    ]
    assert tap.of("software_id")[0].fields["text"] == "EQ7001"


def test_requests_in_msb_order_for_a_unit_configured_so(make: Make) -> None:
    fleet, tap = make(vehicle(request_byte_order="msb"))
    fleet.advance(0.5)
    tap.send("request", {"requested_pgn": PGN_COMPONENT_ID, "da": 30}, request_byte_order="msb")
    fleet.advance(0.1)
    assert len(tap.of("component_id")) == 1


# --- control -------------------------------------------------------------------------------


def last_status(fleet: SimulatedFleet, tap: Tap) -> dict[str, Any]:
    fleet.advance(3.0)
    return tap.of("status")[-1].fields


def test_control_on_off_works_only_while_enabled(make: Make) -> None:
    fleet, tap = make(vehicle(load_12v_a=30.0))
    fleet.advance(3.0)
    tap.send("control", {"can_eq_onoff": "disable"})
    s = last_status(fleet, tap)
    assert s["state_onoff_en"] == "inactive" and s["eq_state_onoff"] == "active"  # ignored
    assert s["eqrn"] == "active"

    tap.send("control", {"can_onoff_en": "enable"})
    tap.send("control", {"can_eq_onoff": "disable"})
    s = last_status(fleet, tap)
    assert s["state_onoff_en"] == "active" and s["eq_state_onoff"] == "inactive"
    assert s["eqrn"] == "inactive"

    tap.send("control", {"can_eq_onoff": "enable"})
    s = last_status(fleet, tap)
    assert s["eq_state_onoff"] == "active" and s["eqrn"] == "active"

    tap.send("control", {"can_jso": "enable"})
    assert last_status(fleet, tap)["state_can_jso"] == "active"
    tap.send("control", {"can_jso": "disable"})
    assert last_status(fleet, tap)["state_can_jso"] == "inactive"


def test_smart_sensor_enable_only_on_70_series(make: Make) -> None:
    fleet, tap = make(vehicle(series=70, rating=60))
    tap.send("control", {"can_ss_msg_en": "disable"}, series=70)
    assert last_status(fleet, tap)["can_ss_msg_on"] == "inactive"
    tap.send("control", {"can_ss_msg_en": "enable"}, series=70)
    assert last_status(fleet, tap)["can_ss_msg_on"] == "active"


def test_80_series_ignores_smart_sensor_bits(make: Make) -> None:
    fleet, tap = make(vehicle(series=80))
    # What a 70-series gateway would send; the 80-series has those bits unused.
    tap.send("control", {"can_ss_msg_en": "disable"}, series=70)
    assert last_status(fleet, tap)["can_ss_msg_on"] == "active"


# --- parameters ----------------------------------------------------------------------------


def test_fault_timer_and_setpoints_change_when_faults_raise(make: Make) -> None:
    fleet, tap = make(vehicle(alternator_on=True))  # 28.2 V at +24 V
    fleet.advance(3.0)
    t_write = fleet.now()
    tap.send("parameters", {"index": 9, "ov_setpoint_v": 27.0, "fault_timer_s": 5})
    run(fleet, 4.5)
    assert tap.of("dm1") == []  # the fault timer has not run out
    run(fleet, 1.0)
    dm1 = tap.of("dm1")
    assert dm1 and dm1_codes(dm1[0]) == ["OVF"]
    assert 5.0 <= dm1[0].ts - t_write <= 5.2
    assert last_status(fleet, tap)["ovf"] == "active"

    # Factory reset: defaults back (OV 30 V), the fault clears with an all-clear.
    tap.send("parameters", {"index": 0, "profile": 2})
    run(fleet, 2.0)
    assert tap.of("dm1")[-1].fields["dtcs"] == []
    unit = fleet.vehicle("V1").unit()
    assert unit.params["ov_setpoint_v"] == DEFAULTS_9["ov_setpoint_v"]
    assert unit.profile == 2
    assert last_status(fleet, tap)["ovf"] == "inactive"


def test_factory_reset_without_a_profile_keeps_the_profile(make: Make) -> None:
    fleet, tap = make()
    unit = fleet.vehicle("V1").unit()
    assert unit.series == 80
    tap.send("parameters", {"index": 0, "profile": 3})
    fleet.advance(0.1)
    assert unit.profile == 3
    tap.send("parameters", {"index": 9, "ov_setpoint_v": 27.0})
    fleet.advance(0.1)
    # 00 FF FF ..: a reset with the profile "not requested, leave unchanged" (the manual).
    frame = compose_id(0xFFD3, GATEWAY_SA), bytes([0x00] + [0xFF] * 7)
    tap.bus.send(can.Message(arbitration_id=frame[0], data=frame[1], is_extended_id=True))
    fleet.advance(0.1)
    assert unit.params["ov_setpoint_v"] == DEFAULTS_9["ov_setpoint_v"]  # the reset happened
    assert unit.profile == 3
    # A profile outside the manuals' 0..4 is ignored too; the reset still happens.
    tap.send("parameters", {"index": 0, "profile": 9})
    fleet.advance(0.1)
    assert unit.profile == 3


def test_out_of_range_setpoint_is_ignored(make: Make) -> None:
    fleet, tap = make()
    unit = fleet.vehicle("V1").unit()
    # The manuals' range is 20..40 V; a unit keeps its setting when given 45 V.
    frame = compose_id(0xFFD3, GATEWAY_SA), bytes([9, 0xC2, 0x01, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF])
    tap.bus.send(can.Message(arbitration_id=frame[0], data=frame[1], is_extended_id=True))
    fleet.advance(0.1)
    assert unit.params["ov_setpoint_v"] == DEFAULTS_9["ov_setpoint_v"]


def test_80_series_stores_battery_parameters(make: Make) -> None:
    fleet, tap = make(vehicle(series=80))
    unit = fleet.vehicle("V1").unit()
    writes: list[dict[str, Any]] = [
        {"index": 1, "cells": 6, "charge_efficiency_pct": 90.0, "peukert_capacity_ah": 120.0},
        {"index": 2, "peukert_exponent": 1.25, "temp_constant": 0.02, "rated_temp_c": 20.0},
        {"index": 3, "endpoint_v": 10.8},
        {"index": 5, "capacity_ah": 120.0, "cranking_current_a": 400.0},
        {"index": 6, "c_rating": 20.0},
        {"index": 7, "soc_12v": 80, "soh_12v": 95, "soc_24v": 81},
        {"index": 8, "soh_24v": 94},
        {"index": 10, "calibration": 1},
    ]
    for fields in writes:
        tap.send("parameters", fields)
    fleet.advance(0.1)
    for fields in writes:
        for key, value in fields.items():
            if key != "index":
                assert unit.params[key] == pytest.approx(value), key
    # Not-requested fields keep their value.
    tap.send("parameters", {"index": 3, "charge_threshold_a": 6.0})
    fleet.advance(0.1)
    assert unit.params["endpoint_v"] == pytest.approx(10.8)
    assert unit.params["charge_threshold_a"] == pytest.approx(6.0)


def test_70_series_ignores_80_series_parameters(make: Make) -> None:
    fleet, tap = make(vehicle(series=70, rating=60))
    unit = fleet.vehicle("V1").unit()
    before = dict(unit.params)
    tap.send("parameters", {"index": 1, "cells": 6})
    tap.send("parameters", {"index": 10, "calibration": 1})
    fleet.advance(0.1)
    assert unit.params == before
    tap.send("parameters", {"index": 9, "uv_setpoint_v": 23.5})
    fleet.advance(0.1)
    assert unit.params["uv_setpoint_v"] == pytest.approx(23.5)


# --- heartbeat and bus faults --------------------------------------------------------------


def test_heartbeat_stuck_then_silent_then_restored(make: Make) -> None:
    fleet, tap = make()
    fleet.advance(10.0)
    fleet.stop_heartbeat("V1", mode="stuck")
    t1 = fleet.now()
    fleet.advance(12.0)
    stuck = [r.fields["heartbeat"] for r in tap.of("heartbeat", since=t1)]
    assert len(stuck) == 4 and len(set(stuck)) == 1
    fleet.stop_heartbeat("V1", mode="silent")
    t2 = fleet.now()
    fleet.advance(12.0)
    assert tap.of("heartbeat", since=t2) == []
    assert len(tap.of("status", since=t2)) == 4  # the rest keeps coming
    fleet.restore_heartbeat("V1")
    t3 = fleet.now()
    fleet.advance(12.0)
    beats = [r.fields["heartbeat"] for r in tap.of("heartbeat", since=t3)]
    assert len(set(beats)) == 2


def test_disconnected_bus_is_silent_both_ways(make: Make) -> None:
    fleet, tap = make()
    fleet.advance(5.0)
    fleet.disconnect_bus("V1")
    t1 = fleet.now()
    tap.send("request", {"requested_pgn": PGN_COMPONENT_ID, "da": 30})
    fleet.advance(20.0)
    assert [r for r in tap.drain() if r.ts >= t1] == []
    fleet.reconnect_bus("V1")
    t2 = fleet.now()
    fleet.advance(6.0)
    assert len(tap.of("status", since=t2)) == 2
    assert tap.of("component_id") == []  # the request sent while cut never arrived
