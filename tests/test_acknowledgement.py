"""J1939-21 Acknowledgement (PGN 59392): decoded from an equalizer, encoded, and matched to the
command it answers."""

from __future__ import annotations

import pytest

from eqgw.protocol.acknowledgement import (
    concerns,
    decode_acknowledgement,
    describe_answer,
    encode_acknowledgement,
)
from eqgw.protocol.decode import FrameDecoder


@pytest.mark.parametrize("control", ["ack", "nack", "access_denied", "cannot_respond"])
def test_encode_decode_round_trip(control: str) -> None:
    can_id, data = encode_acknowledgement(control, 0xFFD2, sa=0x1E, address=0xD8)
    assert can_id == 0x18E8FF1E  # PDU1 to all, J1939-21
    fields = decode_acknowledgement(data, 0xFF)
    assert fields == {
        "control": control,
        "group_function": None,
        "address": 0xD8,
        "acknowledged_pgn": 0xFFD2,
        "da": 0xFF,
    }


def test_a_unit_acknowledgement_is_a_record_and_a_broken_one_is_malformed() -> None:
    dec = FrameDecoder()
    (rec,) = dec.decode(1.0, "c", 0x18E8FF1E, bytes([1, 0xFF, 0xFF, 0xFF, 0xD8, 0xCA, 0xFE, 0]))
    assert rec.name == "acknowledgement" and rec.fields["control"] == "nack"
    assert dec.decode(1.0, "c", 0x18E8FF1E, bytes([9, 0xFF, 0xFF, 0xFF, 0xD8, 0, 0, 0])) == []
    assert dec.decode(1.0, "c", 0x18E8FF1E, bytes([1, 0xFF])) == []
    assert dec.stats.malformed == 2
    assert dec.decode(1.0, "c", 0x18E8FF05, bytes([1, 0xFF, 0xFF, 0xFF, 0xD8, 0, 0, 0])) == []


def test_an_answer_concerns_the_pgn_and_the_requester() -> None:
    mine = decode_acknowledgement(bytes([1, 0xFF, 0xFF, 0xFF, 0xD8, 0xD2, 0xFF, 0]), 0xFF)
    assert concerns(mine, 0xFFD2, 0xD8)
    assert not concerns(mine, 0xFFD3, 0xD8)  # another PGN
    other = decode_acknowledgement(bytes([1, 0xFF, 0xFF, 0xFF, 0x21, 0xD2, 0xFF, 0]), 0xFF)
    assert not concerns(other, 0xFFD2, 0xD8)  # another requester's
    old_style = decode_acknowledgement(bytes([1, 0xFF, 0xFF, 0xFF, 0xFF, 0xD2, 0xFF, 0]), 0xD8)
    assert concerns(old_style, 0xFFD2, 0xD8)
    assert describe_answer(mine) == "NACK for PGN 65490 (0xFFD2)"
