"""Table-driven decoding tests: the manuals' byte examples and hand-computed vectors."""

from __future__ import annotations

from typing import Any

import pytest

from eqgw.protocol.decode import FrameDecoder
from eqgw.protocol.j1939 import compose_id, parse_id, pgn_of


def h(text: str) -> bytes:
    return bytes.fromhex(text.replace(" ", ""))


def one(
    can_id: int, data: str, *, sas: tuple[int, ...] = (30,), **kw: Any
) -> dict[str, Any] | None:
    dec = FrameDecoder(sas, **kw)
    recs = dec.decode(12.5, "can0", can_id, h(data))
    assert len(recs) <= 1
    return recs[0].to_dict() if recs else None


# --- J1939 identifiers -------------------------------------------------------------------


@pytest.mark.parametrize(
    ("can_id", "prio", "pgn", "sa", "da"),
    [
        (0x18FFD41E, 6, 0xFFD4, 0x1E, 0xFF),  # status, PDU2
        (0x18FECA1E, 6, 0xFECA, 0x1E, 0xFF),  # DM1
        (0x18EA1E41, 6, 0xEA00, 0x41, 0x1E),  # request from Clever Devices to the equalizer
        (0x18ECFF1E, 6, 0xEC00, 0x1E, 0xFF),  # BAM TP.CM
        (0x1CEBFF1E, 7, 0xEB00, 0x1E, 0xFF),  # BAM TP.DT at priority 7
        (0x18FFD3D8, 6, 0xFFD3, 0xD8, 0xFF),  # parameters from the system controller
        (0x0CF00400, 3, 0xF004, 0x00, 0xFF),  # EEC1 from the engine
    ],
)
def test_identifier_split_and_compose(can_id: int, prio: int, pgn: int, sa: int, da: int) -> None:
    parts = parse_id(can_id)
    assert (parts.priority, parts.pgn, parts.sa, parts.da) == (prio, pgn, sa, da)
    assert pgn_of(can_id) == pgn
    assert compose_id(pgn, sa, da, prio) == can_id


def test_compose_rejects_bad_input() -> None:
    with pytest.raises(ValueError):
        compose_id(0xEA01, 0x1E)  # PDU1 PGN with a non-zero low byte
    with pytest.raises(ValueError):
        compose_id(0xFFD4, 300)


# --- Status, heartbeat -------------------------------------------------------------------

STATUS_ORDER = [
    "state_can_jso", "state_onoff_en", "ex24f", "ex12f",
    "exgnf", "ovf", "uvf", "imb",
    "eqrn", "eqflt", "io_in_sdn", "vcfl",
    "vcfh", "can_ss_msg_on", "eq_state_onoff", "eq_battflt",
]  # fmt: skip


def test_status_flags_in_byte_and_bit_order() -> None:
    # byte 1 = 0b11_10_01_00: JSO inactive, ONOFF_EN active, EX24F error, EX12F not available
    # byte 2 = 0x40: IMB active; byte 3 = 0x05: EQRN + EQFLT active; byte 4 = 0x14
    rec = one(0x18FFD41E, "E4 40 05 14 FF FF FF FF")
    assert rec is not None
    assert rec["name"] == "status" and rec["pgn"] == 65492 and rec["sa"] == 30
    f = rec["fields"]
    assert list(f) == STATUS_ORDER
    assert f["state_can_jso"] == "inactive"
    assert f["state_onoff_en"] == "active"
    assert f["ex24f"] == "error"
    assert f["ex12f"] == "not_available"
    assert (f["exgnf"], f["ovf"], f["uvf"], f["imb"]) == ("inactive",) * 3 + ("active",)
    assert (f["eqrn"], f["eqflt"], f["io_in_sdn"]) == ("active", "active", "inactive")
    assert (f["vcfh"], f["can_ss_msg_on"], f["eq_state_onoff"], f["eq_battflt"]) == (
        "inactive",
        "active",
        "active",
        "inactive",
    )


def test_status_short_dlc_gives_null_for_missing_bytes() -> None:
    rec = one(0x18FFD41E, "55 00")
    assert rec is not None
    f = rec["fields"]
    assert f["state_can_jso"] == "active" and f["imb"] == "inactive"
    assert all(f[n] is None for n in STATUS_ORDER[8:])


@pytest.mark.parametrize(("byte", "value"), [("FC", 0), ("FD", 1), ("00", 0), ("01", 1)])
def test_heartbeat(byte: str, value: int) -> None:
    rec = one(0x18FFD51E, byte + " FF FF FF FF FF FF FF")
    assert rec is not None and rec["fields"] == {"heartbeat": value}


# --- Voltages and currents -----------------------------------------------------------------


def test_voltages_hand_vector() -> None:
    # v12 0x09D8=2520 -> 12.600 V, v24 0x13B0=5040 -> 25.200 V,
    # i12 0x7CBA=31930 -> -3.50 A, i24 0x7DC8=32200 -> 10.00 A
    rec = one(0x18FFD61E, "D8 09 B0 13 BA 7C C8 7D")
    assert rec is not None
    assert rec["fields"] == {"v12": 12.6, "v24": 25.2, "i12": -3.5, "i24": 10.0}


def test_voltages_resolution_is_exact() -> None:
    # 0x0A01 = 2561 * 0.005 = 12.805 exactly, not 12.805000000000001
    rec = one(0x18FFD61E, "01 0A FF FA 00 00 FF FA")
    assert rec is not None
    assert rec["fields"] == {"v12": 12.805, "v24": 321.275, "i12": -1600.0, "i24": 1612.75}


def test_voltages_not_available_and_short_dlc() -> None:
    rec = one(0x18FFD61E, "00 FB FF FF")
    assert rec is not None
    assert rec["fields"] == {"v12": None, "v24": None, "i12": None, "i24": None}
    rec = one(0x18FFD61E, "D8 09")
    assert rec is not None
    assert rec["fields"] == {"v12": 12.6, "v24": None, "i12": None, "i24": None}


def test_70_series_voltages_have_no_currents() -> None:
    dec = FrameDecoder((30,))
    dec.decode(1.0, "can0", 0x18FEEB1E, h("2A 45 51 37 30 30 31 2A"))  # *EQ7001*
    assert dec.series_of("can0", 30) == 70
    recs = dec.decode(2.0, "can0", 0x18FFD61E, h("D8 09 B0 13 00 00 00 00"))
    assert recs[0].fields == {"v12": 12.6, "v24": 25.2, "i12": None, "i24": None}
    # Another unit on another bus is still read by the 80-series layout.
    recs = dec.decode(2.0, "can1", 0x18FFD61E, h("D8 09 B0 13 00 7D 00 7D"))
    assert recs[0].fields["i12"] == 0.0


# --- Battery states --------------------------------------------------------------------


def test_battery_states_index_1_and_3() -> None:
    # SOCach 0x03BB=955 -> 95.5 %, SOH 0x0370=880 -> 88.0 %, run time 0x00F1=241 -> 120.5 min
    rec = one(0x18FFD91E, "01 BB 03 70 03 F1 00 FF")
    assert rec is not None
    assert rec["fields"] == {
        "index": 1,
        "battery": "12v",
        "soc_achievable": 95.5,
        "soh": 88.0,
        "runtime_min": 120.5,
    }
    rec = one(0x18FFD91E, "03 E8 03 E9 03 00 00 FF")
    assert rec is not None
    # SOH raw 1001 = 100.1 % is invalid -> null; SOCach 100.0 % is valid
    assert rec["fields"] == {
        "index": 3,
        "battery": "24v",
        "soc_achievable": 100.0,
        "soh": None,
        "runtime_min": 0.0,
    }


def test_battery_states_index_2_and_4() -> None:
    rec = one(0x18FFD91E, "02 10 27 2C 01 84 03 FF")
    assert rec is not None
    assert rec["fields"] == {
        "index": 2,
        "battery": "12v",
        "runtime_temp_adj_min": 5000.0,
        "dod": 30.0,
        "soc": 90.0,
    }
    rec = one(0x18FFD91E, "04 FF FF FF FF 00 FB FF")
    assert rec is not None
    assert rec["fields"] == {
        "index": 4,
        "battery": "24v",
        "runtime_temp_adj_min": None,
        "dod": None,
        "soc": None,
    }


def test_battery_status_index_5_temperature() -> None:
    # temperature raw 0x762D = 30253 -> 30253 * 0.1 - 3000 = 25.3 degC
    rec = one(0x18FFD91E, "05 01 02 03 FB 2D 76 FF")
    assert rec is not None
    assert rec["fields"] == {
        "index": 5,
        "major_12v": 1,
        "minor_12v": 2,
        "major_24v": 3,
        "minor_24v": None,  # 1-byte values above 0xFA are not available
        "temperature_c": 25.3,
        "temperature_raw": 30253,
        "temperature_implausible": False,
    }
    rec = one(0x18FFD91E, "05 00 00 00 00 00 00 FF")
    assert rec is not None
    assert rec["fields"]["temperature_c"] == -3000.0
    assert rec["fields"]["temperature_implausible"] is True


@pytest.mark.parametrize("data", ["00 01 02 03 04", "06 00 00 00 00 00 00 00", "FF", "", "01"])
def test_battery_states_unknown_index_or_no_field_is_malformed(data: str) -> None:
    dec = FrameDecoder()
    assert dec.decode(0.0, None, 0x18FFD91E, h(data)) == []
    assert dec.stats.malformed == 1 and dec.stats.records == 0


# --- DM1 -----------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("data", "dtcs"),
    [
        ("00 FF 00 00 00 00 FF FF", []),  # all-clear
        ("08 00 A8 00 00 05 00 00", [(168, 0, 5, "OVF")]),  # tables pad with 0x00
        ("08 00 A8 00 01 05 FF FF", [(168, 1, 5, "UVF")]),  # text pads with 0xFF
        ("08 00 00 F1 E0 02 00 00", [(520448, 0, 2, "IMB")]),
        ("08 00 01 F1 E1 7F FF FF", [(520449, 1, 127, "EQFLT")]),
    ],
)
def test_dm1_single_frames_from_the_manuals(data: str, dtcs: list[tuple[Any, ...]]) -> None:
    rec = one(0x18FECA1E, data)
    assert rec is not None and rec["name"] == "dm1" and rec["pgn"] == 65226
    got = [(d["spn"], d["fmi"], d["oc"], d["code"]) for d in rec["fields"]["dtcs"]]
    assert got == dtcs
    assert rec["fields"]["lamps"]["awl"] == (2 if dtcs else 0)


def test_dm1_bam_as_laid_out_in_the_manual() -> None:
    dec = FrameDecoder()
    # Three DTCs: OVF OC 1, IMB OC 2, EQFLT OC 3 -> 2 + 12 = 14 bytes in 2 packets
    frames = [
        (0x18ECFF1E, "20 0E 00 02 FF CA FE 00"),
        (0x1CEBFF1E, "01 08 00 A8 00 00 01 00"),
        (0x1CEBFF1E, "02 F1 E0 02 01 F1 E1 03"),
    ]
    out = []
    for i, (cid, data) in enumerate(frames):
        out += dec.decode(10.0 + i * 0.05, "can0", cid, h(data))
    assert len(out) == 1
    rec = out[0].to_dict()
    assert rec["ts"] == 10.1  # timestamp of the last packet
    assert rec["pgn"] == 65226 and rec["name"] == "dm1"
    assert [(d["code"], d["oc"]) for d in rec["fields"]["dtcs"]] == [
        ("OVF", 1),
        ("IMB", 2),
        ("EQFLT", 3),
    ]
    assert dec.stats.transfers_completed == 1 and dec.stats.transport_frames == 3


def test_bam_from_another_node_is_ignored() -> None:
    dec = FrameDecoder()
    for cid, data in [
        (0x18ECFF00, "20 0E 00 02 FF CA FE 00"),
        (0x1CEBFF00, "01 08 00 A8 00 00 01 00"),
        (0x1CEBFF00, "02 F1 E0 02 01 F1 E1 03"),
    ]:
        assert dec.decode(1.0, "can0", cid, h(data)) == []
    assert dec.stats.ignored == 3 and dec.stats.records == 0


# --- Identification -------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("can_id", "data", "name", "fields"),
    [
        (
            0x18FEEB1E,
            "2A 45 51 38 30 30 31 2A",
            "component_id",
            {"text": "EQ8001", "series": 80, "revision": 1},
        ),
        (
            0x18FEED1E,  # the 70-series manual's misprinted id, accepted for "*EQ"
            "2A 45 51 37 30 30 31 2A",
            "component_id",
            {"text": "EQ7001", "series": 70, "revision": 1},
        ),
        (
            0x18FEDA1E,
            "31 45 51 38 30 30 31 2A",
            "software_id",
            {"text": "EQ8001", "series": 80, "revision": 1, "field_count": 1},
        ),
        (
            0x18FEDA1E,
            "31 45 51 37 30 30 32 2A",
            "software_id",
            {"text": "EQ7002", "series": 70, "revision": 2, "field_count": 1},
        ),
    ],
)
def test_identification(can_id: int, data: str, name: str, fields: dict[str, Any]) -> None:
    rec = one(can_id, data)
    assert rec is not None and rec["name"] == name and rec["fields"] == fields


def test_feed_pgn_without_eq_prefix_is_not_component_id() -> None:
    assert one(0x18FEED1E, "00 11 22 33 44 55 66 77") is None


# --- Frames to the equalizer ------------------------------------------------------------------


def test_control_from_any_source_address() -> None:
    # byte 1 = 0b11_11_01_01: JSO enable, ONOFF_EN enable, EQ_ONOFF no action, SS no action
    rec = one(0x18FFD2D8, "F5 FF FF FF FF FF FF FF")
    assert rec is not None and rec["sa"] == 0xD8
    assert rec["fields"] == {
        "can_jso": "enable",
        "can_onoff_en": "enable",
        "can_eq_onoff": "no_action",
        "can_ss_msg_en": "no_action",
    }
    rec = one(0x18FFD241, "E8 FF FF FF FF FF FF FF")  # from SA 0x41: still a control frame
    assert rec is not None
    assert rec["fields"] == {
        "can_jso": "disable",
        "can_onoff_en": "reserved",
        "can_eq_onoff": "reserved",
        "can_ss_msg_en": "no_action",
    }


@pytest.mark.parametrize(
    ("data", "fields"),
    [
        ("00 02 00 FF FF FF FF FF", {"index": 0, "profile": 2}),
        ("00 FF FF FF FF FF FF FF", {"index": 0, "profile": None}),  # 70-series: no profile
        (
            "01 0C 00 52 03 A8 61 FF",  # 12 cells, 85.0 %, 250.00 Ah
            {"index": 1, "cells": 12, "charge_efficiency_pct": 85.0, "peukert_capacity_ah": 250.0},
        ),
        (
            # n 1.250, Tc 0.010 at bytes 4-5 (erratum), Tr 25.00 degC
            "02 E2 04 0A 00 C4 09 FF",
            {"index": 2, "peukert_exponent": 1.25, "temp_constant": 0.01, "rated_temp_c": 25.0},
        ),
        (
            # Ve 10.500 V, thC 5.00 A = (5+327.68)/0.01 = 33268, thD -5.00 A = 32268
            "03 04 29 F4 81 0C 7E FF",
            {
                "index": 3,
                "endpoint_v": 10.5,
                "charge_threshold_a": 5.0,
                "discharge_threshold_a": -5.0,
            },
        ),
        (
            # thBC 50.00 A = 37768, thS 150.0 A = 34268, thCS 300.0 A = 35768
            "04 88 93 DC 85 B8 8B FF",
            {
                "index": 4,
                "boost_charge_threshold_a": 50.0,
                "start_threshold_a": 150.0,
                "cold_start_threshold_a": 300.0,
            },
        ),
        (
            # Ahr 200.00, BCC 350.0 A, BVMT 1.250 V at bytes 6-7 little-endian (erratum)
            "05 20 4E AC 0D E2 04 FF",
            {"index": 5, "capacity_ah": 200.0, "cranking_current_a": 350.0, "voltage_trip_v": 1.25},
        ),
        (
            # Chr 10.00 (a ratio), BCLfsd 80.0 A, BCHfsd 600.0 A (0.1 A/bit)
            "06 E8 03 20 03 70 17 FF",
            {"index": 6, "c_rating": 10.0, "current_low_fsd_a": 80.0, "current_high_fsd_a": 600.0},
        ),
        ("07 50 00 5A 00 FF FF FF", {"index": 7, "soc_12v": 80, "soh_12v": 90, "soc_24v": None}),
        ("08 64 00 FF FF FF FF FF", {"index": 8, "soh_24v": 100}),
        (
            "09 27 01 DC 00 0A 00 FF",
            {"index": 9, "ov_setpoint_v": 29.5, "uv_setpoint_v": 22.0, "fault_timer_s": 10},
        ),
        ("0A 02 FF FF FF FF FF FF", {"index": 10, "calibration": 2}),  # code in byte 2
    ],
)
def test_parameters_every_index(data: str, fields: dict[str, Any]) -> None:
    rec = one(0x18FFD3D8, data)
    assert rec is not None and rec["name"] == "parameters" and rec["fields"] == fields


def test_parameters_unknown_index_is_malformed() -> None:
    dec = FrameDecoder()
    assert dec.decode(0.0, None, 0x18FFD3D8, h("0B 00 00 00 00 00 00 00")) == []
    assert dec.stats.malformed == 1


@pytest.mark.parametrize(
    ("can_id", "data", "order", "expected"),
    [
        (0x18EA1E41, "CA FE 00", "lsb", {"requested_pgn": 0xFECA, "da": 30}),
        (0x18EAFFD8, "EB FE 00 FF FF FF FF FF", "lsb", {"requested_pgn": 0xFEEB, "da": 255}),
        (0x18EA1ED8, "00 FE DA", "msb", {"requested_pgn": 0xFEDA, "da": 30}),
    ],
)
def test_request(can_id: int, data: str, order: str, expected: dict[str, int]) -> None:
    rec = one(can_id, data, request_byte_order=order)
    assert rec is not None and rec["name"] == "request" and rec["fields"] == expected


def test_request_to_another_node_is_ignored() -> None:
    assert one(0x18EA00D8, "CA FE 00") is None


# --- What is not an equalizer message ---------------------------------------------------------


def test_other_vendors_proprietary_pgns_are_ignored() -> None:
    dec = FrameDecoder((30,))
    for pgn_low in range(0xD4, 0xDA):
        assert dec.decode(0.0, None, 0x18FF0040 | (pgn_low << 8), h("00" * 8)) == []
    assert dec.stats.ignored == 6


def test_second_unit_at_another_sa() -> None:
    dec = FrameDecoder((30, 31))
    recs = dec.decode(0.0, "can0", 0x18FFD61F, h("D8 09 B0 13 BA 7C C8 7D"))
    assert recs[0].sa == 31
    assert FrameDecoder((30,)).decode(0.0, "can0", 0x18FFD61F, h("D8 09")) == []


def test_eleven_bit_remote_and_error_frames_are_ignored() -> None:
    dec = FrameDecoder()
    assert dec.decode(0.0, None, 0x1E, h("00"), is_extended=False) == []
    assert dec.decode(0.0, None, 0x18FFD41E, b"", is_remote=True) == []
    assert dec.decode(0.0, None, 0x18FFD41E, h("00"), is_error=True) == []
    assert dec.stats.ignored == 3 and dec.stats.malformed == 0


def test_empty_equalizer_frames_are_malformed() -> None:
    dec = FrameDecoder()
    for cid in (0x18FFD41E, 0x18FFD51E, 0x18FFD61E, 0x18FECA1E, 0x18FEEB1E, 0x18FEDA1E):
        assert dec.decode(0.0, None, cid, b"") == []
    assert dec.stats.malformed == 6


def test_only_filters_records_but_counts_frames() -> None:
    dec = FrameDecoder(only=["voltages"])
    assert dec.decode(0.0, None, 0x18FFD51E, h("FC")) == []
    assert len(dec.decode(0.0, None, 0x18FFD61E, h("D8 09"))) == 1
    assert dec.stats.frames == 2 and dec.stats.records == 1


def test_records_do_not_share_mutable_fields() -> None:
    dec = FrameDecoder()
    a = dec.decode(0.0, None, 0x18FECA1E, h("08 00 A8 00 00 05 FF FF"))[0]
    a.fields["dtcs"][0]["oc"] = 99
    a.fields["lamps"]["awl"] = 0
    b = dec.decode(1.0, None, 0x18FECA1E, h("08 00 A8 00 00 05 FF FF"))[0]
    assert b.fields["dtcs"][0]["oc"] == 5 and b.fields["lamps"]["awl"] == 2
