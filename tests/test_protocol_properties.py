"""Property tests: encode/decode round trips to the bit, no crash on any input, cantools agrees."""

from __future__ import annotations

import functools
from typing import Any

import cantools
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from eqgw.protocol import dbc
from eqgw.protocol.decode import FrameDecoder, multiplexed_signals
from eqgw.protocol.encode import encode
from eqgw.protocol.j1939 import compose_id

SA = 30
ALL_ONES_16 = 0xFFFF


def _raw_strategy(message: str, signal: str) -> st.SearchStrategy[int]:
    rule = dbc.signal_rules(message)[signal]
    if rule.choices is not None:
        return st.integers(0, 3)
    if rule.length == 16:
        hi = 0xFAFF
        if message == "battery_states" and rule.unit == "%":
            hi = 1000  # above 100.0 % is invalid and decodes to null
        return st.one_of(st.integers(0, hi), st.just(ALL_ONES_16))
    if rule.length == 8:
        return st.one_of(st.integers(0, 0xFA), st.just(0xFF))
    return st.integers(0, (1 << rule.length) - 1)


# Built once per message and index: a test draws from it at each example, and a strategy
# built anew each time is validated anew by Hypothesis.
@functools.cache
def _frame_strategy(message: str, index: int | None = None) -> st.SearchStrategy[bytes]:
    msg = dbc.message(message)
    if index is None:
        names = [s.name for s in msg.signals]
    else:
        names = multiplexed_signals(message, index)
    strategies = {n: _raw_strategy(message, n) for n in names}

    @st.composite
    def build(draw: st.DrawFn) -> bytes:
        raw: dict[str, int] = {n: draw(s) for n, s in strategies.items()}
        if index is not None:
            raw["index"] = index
        data: bytes = msg.encode(raw, scaling=False, padding=True, strict=False)
        return data

    return build()


CASES: list[tuple[str, int | None, int]] = [
    ("status", None, 0x18FFD41E),
    ("heartbeat", None, 0x18FFD51E),
    ("voltages", None, 0x18FFD61E),
    *[("battery_states", i, 0x18FFD91E) for i in range(1, 6)],
    ("control", None, 0x18FFD2D8),
    *[("parameters", i, 0x18FFD3D8) for i in range(0, 11)],
]


@pytest.mark.parametrize(("message", "index", "can_id"), CASES)
@settings(max_examples=150, deadline=None)
@given(data=st.data())
def test_decode_then_encode_gives_the_same_bytes(
    message: str, index: int | None, can_id: int, data: st.DataObject
) -> None:
    frame = data.draw(_frame_strategy(message, index))
    dec = FrameDecoder((SA,))
    recs = dec.decode(0.0, None, can_id, frame)
    assert len(recs) == 1, dec.stats
    rec = recs[0]
    if message == "heartbeat":
        # bits 2-7 are unused: only the two heartbeat bits round-trip
        frames = encode("heartbeat", rec.fields, sa=SA)
        assert frames[0][1][0] & 0x03 == frame[0] & 0x03
        return
    sa = can_id & 0xFF
    series = 70 if message == "control" else 80
    frames = encode(rec.name, rec.fields, sa=sa, series=series)
    assert frames == [(can_id, frame)]


@settings(max_examples=3000, deadline=None)
@given(
    can_id=st.integers(0, (1 << 29) - 1),
    data=st.binary(max_size=8),
    extended=st.booleans(),
)
def test_any_bytes_under_any_identifier_never_raise(
    can_id: int, data: bytes, extended: bool
) -> None:
    dec = FrameDecoder((SA, 31))
    dec.decode(0.0, "x", can_id, data, is_extended=extended)
    dec.decode(0.0, "x", (can_id & ~0xFF) | SA, data)  # same PGN from the equalizer
    # every frame lands in exactly one of the frame counters
    assert dec.stats.frames == 2


EQ_PGNS = [0xFFD4, 0xFFD5, 0xFFD6, 0xFFD9, 0xFECA, 0xFEEB, 0xFEED, 0xFEDA, 0xFFD2, 0xFFD3]


@settings(max_examples=2000, deadline=None)
@given(pgn=st.sampled_from(EQ_PGNS), data=st.binary(max_size=8))
def test_any_payload_of_an_equalizer_pgn_never_raises(pgn: int, data: bytes) -> None:
    dec = FrameDecoder()
    for rec in dec.decode(0.0, None, compose_id(pgn, SA), data):
        assert rec.sa == SA


# --- cross-check with cantools' own decoding of the shipped DBC ------------------------------

_DB = cantools.database.load_file(
    str(__import__("pathlib").Path(dbc.__file__).with_name("vanner_equalizer.dbc"))
)


def _cantools_fields(message: str, data: bytes) -> dict[str, Any]:
    msg = _DB.get_message_by_name(message)
    out: dict[str, Any] = msg.decode(data, decode_choices=True, scaling=True)
    return out


@pytest.mark.parametrize(("message", "index", "can_id"), CASES)
@settings(max_examples=100, deadline=None)
@given(data=st.data())
def test_cantools_agrees_with_records(
    message: str, index: int | None, can_id: int, data: st.DataObject
) -> None:
    frame = data.draw(_frame_strategy(message, index))
    rec = FrameDecoder().decode(0.0, None, can_id, frame)[0]
    reference = _cantools_fields(message, frame)
    suffix = {1: "_12v", 2: "_12v", 3: "_24v", 4: "_24v"}.get(index or 0, "")
    compared = nulls = 0
    for dbc_name, ref in reference.items():
        # The file's signal names are unique across messages; records use the dictionary's.
        name = dbc.field_name(message, dbc_name)
        if name == "index":
            assert rec.fields["index"] == getattr(ref, "value", ref)
            continue
        key = name[: -len(suffix)] if suffix and name.endswith(suffix) else name
        ours = rec.fields[key]
        if ours is None:
            # A J1939 null: the DBC's value descriptions name it, so CAN tools show no number.
            assert str(ref) in ("not_available", "not_requested"), (name, ref)
            nulls += 1
            continue
        if isinstance(ours, str):
            assert str(ref) == ours
        else:
            assert ours == pytest.approx(float(getattr(ref, "value", ref)), abs=1e-9)
        compared += 1
    assert compared + nulls == len([n for n in reference if dbc.field_name(message, n) != "index"])
