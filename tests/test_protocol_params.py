"""Parameter write validation against the manuals' ranges and series, and its encoding."""

from __future__ import annotations

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from eqgw.protocol.decode import FrameDecoder
from eqgw.protocol.params import PARAMETERS, encode_parameter_write, validate_parameter_write


def test_every_parameter_of_spec_notes_is_known() -> None:
    expected = {
        0: ["profile"],
        1: ["cells", "charge_efficiency_pct", "peukert_capacity_ah"],
        2: ["peukert_exponent", "temp_constant", "rated_temp_c"],
        3: ["endpoint_v", "charge_threshold_a", "discharge_threshold_a"],
        4: ["boost_charge_threshold_a", "start_threshold_a", "cold_start_threshold_a"],
        5: ["capacity_ah", "cranking_current_a", "voltage_trip_v"],
        6: ["c_rating", "current_low_fsd_a", "current_high_fsd_a"],
        7: ["soc_12v", "soh_12v", "soc_24v"],
        8: ["soh_24v"],
        9: ["ov_setpoint_v", "uv_setpoint_v", "fault_timer_s"],
        10: ["calibration"],
    }
    got: dict[int, list[str]] = {}
    for spec in PARAMETERS.values():
        got.setdefault(spec.index, []).append(spec.name)
    assert got == expected


@pytest.mark.parametrize(
    ("values", "series", "reasons"),
    [
        ({"ov_setpoint_v": 29.5, "fault_timer_s": 10}, 70, []),
        ({"ov_setpoint_v": 29.5, "fault_timer_s": 10}, 80, []),
        ({"ov_setpoint_v": 29.5}, None, []),  # index 9: both series accept it
        ({"ov_setpoint_v": 19.9}, 80, ["ov_setpoint_v: 19.9 V is outside 20..40 V"]),
        ({"uv_setpoint_v": 40.1}, 80, ["uv_setpoint_v: 40.1 V is outside 20..40 V"]),
        ({"fault_timer_s": 61}, 70, ["fault_timer_s: 61 s is outside 0..60 s"]),
        ({"fault_timer_s": -1}, 70, ["fault_timer_s: -1 s is outside 0..60 s"]),
        ({"soc_12v": 101}, 80, ["soc_12v: 101 % is outside 0..100 %"]),
        ({"profile": 5}, 80, ["profile: 5 is outside 0..4"]),
        ({"profile": 2}, 70, ["profile: not supported by the 70-series (index 0)"]),
        ({"cells": 6}, 70, ["cells: not supported by the 70-series (index 1)"]),
        ({"cells": 6}, None, ["cells: not supported by an unknown series (index 1)"]),
        (
            {"ov_setpoint_v": 29.55},
            80,
            ["ov_setpoint_v: 29.55 is not a multiple of the 0.1 resolution"],
        ),
        ({"ov_setpoint_v": "29"}, 80, ["ov_setpoint_v: '29' is not a number"]),
        ({"ov_setpoint_v": True}, 80, ["ov_setpoint_v: True is not a number"]),
        ({"ov_setpoint_v": float("nan")}, 80, ["ov_setpoint_v: must be finite"]),
        ({"bogus": 1}, 80, ["bogus: unknown parameter"]),
        ({}, 80, ["no parameter given"]),
        ({"factory_reset": True}, 70, []),
        ({"factory_reset": False}, 70, ["factory_reset: must be true when given"]),
        ({"calibration": 3}, 80, ["calibration: 3 is outside 1..2"]),
    ],
)
def test_validation_reasons(
    values: dict[str, object], series: int | None, reasons: list[str]
) -> None:
    assert validate_parameter_write(values, series) == reasons


def test_write_encodes_one_frame_per_index_with_not_requested_elsewhere() -> None:
    frames = encode_parameter_write(
        {"fault_timer_s": 10, "ov_setpoint_v": 29.5, "soc_12v": 80}, sa=0xD8, series=80
    )
    assert frames == [
        (0x18FFD3D8, bytes.fromhex("07 50 00 FF FF FF FF FF".replace(" ", ""))),
        (0x18FFD3D8, bytes.fromhex("09 27 01 FF FF 0A 00 FF".replace(" ", ""))),
    ]


def test_factory_reset_on_70_series_is_index_0_with_nothing_requested() -> None:
    frames = encode_parameter_write({"factory_reset": True}, sa=0xD8, series=70)
    assert frames == [(0x18FFD3D8, bytes.fromhex("00FFFFFFFFFFFFFF"))]


def test_invalid_write_is_not_encoded() -> None:
    with pytest.raises(ValueError, match="outside"):
        encode_parameter_write({"ov_setpoint_v": 50.0}, sa=0xD8, series=80)


@settings(max_examples=300, deadline=None)
@given(
    name=st.sampled_from(sorted(PARAMETERS)),
    fraction=st.floats(0.0, 1.0),
)
def test_any_valid_value_round_trips_through_the_bus(name: str, fraction: float) -> None:
    spec = PARAMETERS[name]
    steps = round((spec.maximum - spec.minimum) / spec.resolution * fraction)
    value = round(spec.minimum + steps * spec.resolution, 6)
    if spec.resolution == 1:
        value = int(value)
    assert validate_parameter_write({name: value}, 80) == []
    frames = encode_parameter_write({name: value}, sa=0xD8, series=80)
    assert len(frames) == 1
    rec = FrameDecoder().decode(0.0, None, *frames[0])[0]
    assert rec.fields[name] == pytest.approx(value, abs=spec.resolution / 1000)
    others = {k: v for k, v in rec.fields.items() if k not in ("index", name)}
    assert all(v is None for v in others.values())
