"""Edges found by third-party tools and real truck traffic: long payloads, empty parameter
frames, other nodes' requests (decoder level; logs and the DBC have their own tests)."""

from __future__ import annotations

import can
import pytest

from eqgw.forward.central import ForwardRefused, to_messages
from eqgw.protocol.decode import ANSWERED_PGNS, FrameDecoder


def h(text: str) -> bytes:
    return bytes.fromhex(text.replace(" ", ""))


# --- payloads longer than a J1939 frame --------------------------------------------------


@pytest.mark.parametrize("length", [9, 12, 32, 64])
@pytest.mark.parametrize(
    "can_id",
    [0x18FFD61E, 0x18FFD41E, 0x18FECA1E, 0x18FFD3D8, 0x18FFD2D8, 0x18EA1ED8, 0x0CF00400],
)
def test_more_than_8_data_bytes_is_malformed_never_decoded(can_id: int, length: int) -> None:
    dec = FrameDecoder((30,))
    data = bytes(range(0xD8, 0xD8 + length // 2)) * 2 + b"\x00" * (length % 2)
    assert dec.decode(0.0, "can0", can_id, data) == []
    assert dec.stats.malformed == 1 and dec.stats.records == 0 and dec.stats.frames == 1


def test_fd_frame_from_a_remembered_other_node_is_malformed_too() -> None:
    dec = FrameDecoder((30,))
    eec1 = can.Message(arbitration_id=0x0CF00400, data=h("00" * 8), is_extended_id=True)
    assert dec.decode_message(eec1) == []  # remembered as another node's id
    fd = can.Message(arbitration_id=0x0CF00400, data=h("00" * 64), is_extended_id=True, is_fd=True)
    assert dec.decode_message(fd) == []
    assert (dec.stats.ignored, dec.stats.malformed) == (1, 1)


def test_voltages_with_64_bytes_is_not_a_record() -> None:
    msg = can.Message(
        arbitration_id=0x18FFD61E, data=bytes(range(64)), is_extended_id=True, is_fd=True
    )
    dec = FrameDecoder((30,))
    assert dec.decode_message(msg) == []
    assert dec.stats.malformed == 1


def test_forward_upload_refuses_frames_longer_than_8_bytes() -> None:
    assert len(to_messages([(1.0, 0x18FFD61E, "d809b013ba7cc87d", 1)], "b")) == 1
    with pytest.raises(ForwardRefused, match="more than 8 data bytes"):
        to_messages([(1.0, 0x18FFD61E, "00" * 9, 1)], "b")


# --- a parameters frame with no field --------------------------------------------------


@pytest.mark.parametrize("index", range(0, 11))
def test_parameters_frame_with_only_the_index_and_a_partial_byte_is_malformed(
    index: int,
) -> None:
    dec = FrameDecoder()
    # Index 10's field is one byte: the index alone carries nothing; for 0-9 one more byte
    # is half a 16-bit value.
    data = bytes([index]) if index == 10 else bytes([index, 0x00])
    assert dec.decode(0.0, None, 0x18FFD3D8, data) == []
    assert dec.stats.malformed == 1 and dec.stats.records == 0


def test_parameters_frame_with_the_first_field_is_a_record() -> None:
    dec = FrameDecoder()
    rec = dec.decode(0.0, None, 0x18FFD3D8, h("01 04 00"))[0]
    assert rec.fields == {
        "index": 1,
        "cells": 4,
        "charge_efficiency_pct": None,
        "peukert_capacity_ah": None,
    }
    # A factory reset without a profile (all ones: "not requested") is a record, not nulls.
    rec = dec.decode(0.0, None, 0x18FFD3D8, h("00 FF FF FF FF FF FF FF"))[0]
    assert rec.fields == {"index": 0, "profile": None}


# --- requests from any node ------------------------------------------------------------


def test_global_request_for_a_pgn_no_equalizer_answers_is_ignored() -> None:
    dec = FrameDecoder((30,))
    # SA 49 asks everyone for PGN 65257 (fuel consumption), as on a truck with no equalizer.
    for _ in range(3):
        assert dec.decode(0.0, "can0", 0x18EAFF31, h("E9 FE 00")) == []
    assert dec.stats.ignored == 3 and dec.stats.records == 0 and dec.stats.malformed == 0
    # The same id asking for DM1 right after is a request record (the id is not blacklisted).
    msg = can.Message(arbitration_id=0x18EAFF31, data=h("CA FE 00"), is_extended_id=True)
    recs = dec.decode_message(msg)
    assert [r.fields for r in recs] == [{"requested_pgn": 0xFECA, "da": 255}]


@pytest.mark.parametrize("pgn", sorted(ANSWERED_PGNS))
def test_global_request_for_what_an_equalizer_answers_is_a_record(pgn: int) -> None:
    dec = FrameDecoder((30,))
    recs = dec.decode(0.0, "can0", 0x18EAFF31, pgn.to_bytes(3, "little"))
    assert [r.fields for r in recs] == [{"requested_pgn": pgn, "da": 255}]


def test_answered_pgns_are_the_manuals() -> None:
    # "the Request Message supports requests for DM1, Software ID, and Component ID
    # messages" (both manuals), plus the 70-series manual's misprinted Component ID PGN.
    assert {0xFECA, 0xFEDA, 0xFEEB, 0xFEED} == ANSWERED_PGNS


def test_request_to_an_equalizer_counts_whatever_it_asks() -> None:
    dec = FrameDecoder((30, 31))
    recs = dec.decode(0.0, "can0", 0x18EA1F31, h("E9 FE 00"))
    assert [r.fields for r in recs] == [{"requested_pgn": 0xFEE9, "da": 31}]
    assert dec.decode(0.0, "can0", 0x18EA2031, h("CA FE 00")) == []  # to SA 32: not ours


def test_request_msb_order_is_checked_in_that_order() -> None:
    dec = FrameDecoder((30,), request_byte_order="msb")
    assert len(dec.decode(0.0, "can0", 0x18EAFF31, h("00 FE CA"))) == 1
    assert dec.decode(0.0, "can0", 0x18EAFF31, h("00 FE E9")) == []


@pytest.mark.parametrize("ts", [float("nan"), float("inf"), float("-inf")])
def test_a_frame_without_a_finite_time_is_malformed(ts: float) -> None:
    # Any log format (a .csv or .asc can carry "nan" too): never a record with "ts": null.
    dec = FrameDecoder((30,))
    assert dec.decode(ts, "can0", 0x18FFD61E, h("D8 09 B0 13 BA 7C C8 7D")) == []
    assert dec.stats.malformed == 1
