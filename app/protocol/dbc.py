"""The shipped DBC, loaded once with cantools, and the per-signal rules a DBC cannot express."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from decimal import Decimal
from functools import cache
from importlib import resources
from typing import cast

import cantools
from cantools.database.can import Database, Message
from cantools.database.can.signal import Signal
from cantools.database.diagnostics import Data
from cantools.database.utils import decode_data
from cantools.typechecking import Formats

from eqgw.jsontypes import JSONObject

DBC_RESOURCE = "vanner_equalizer.dbc"


def dbc_text() -> str:
    """The DBC file's text, as shipped in the package."""
    return resources.files("eqgw.protocol").joinpath(DBC_RESOURCE).read_text(encoding="utf-8")


# Signal names in the DBC file are unique across messages (ARXML exports need that: canmatrix
# files every signal under one path) while records keep the signal dictionary's names. Per
# message, DBC signal name -> record field name; `database()` applies it.
FIELD_OF_SIGNAL: dict[str, dict[str, str]] = {
    "heartbeat": {"heartbeat_state": "heartbeat"},
    "battery_states": {"bs_index": "index"},
    "parameters": {
        "param_index": "index",
        "param_soc_12v": "soc_12v",
        "param_soh_12v": "soh_12v",
        "param_soc_24v": "soc_24v",
        "param_soh_24v": "soh_24v",
    },
    "component_id_70": {"model_ascii_70": "model_ascii"},
    "tp_cm": {"tp_control": "control"},
}


def field_name(message_name: str, signal_name: str) -> str:
    """The record field (signal dictionary) name of a DBC signal."""
    return FIELD_OF_SIGNAL.get(message_name, {}).get(signal_name, signal_name)


@cache
def database() -> Database:
    """The equalizer database (parsed once per process), its signals named as record fields."""
    db = cantools.database.load_string(dbc_text(), database_format="dbc", strict=True)
    assert isinstance(db, Database)
    for msg in db.messages:
        renames = FIELD_OF_SIGNAL.get(msg.name)
        if renames:
            for sig in msg.signals:
                sig.name = renames.get(sig.name, sig.name)
                if sig.multiplexer_signal is not None:
                    sig.multiplexer_signal = renames.get(
                        sig.multiplexer_signal, sig.multiplexer_signal
                    )
            msg.refresh()
    return db


@dataclass(frozen=True, slots=True)
class SignalRule:
    """How one DBC signal becomes a record field: scaling, null range, choices, rounding."""

    name: str
    length: int
    scale: float
    offset: float
    decimals: int
    minimum: float | None
    maximum: float | None
    unit: str
    choices: dict[int, str] | None
    is_integer: bool

    def to_physical(self, raw: int) -> str | float | None:
        """Apply J1939 "not available" ranges, value tables and scaling to a raw value."""
        if self.choices is not None:
            return self.choices.get(raw, str(raw))
        if self.length == 16 and raw >= 0xFB00:
            return None
        if self.length == 8 and raw > 0xFA:
            return None
        if self.is_integer:
            return raw
        return round(raw * self.scale + self.offset, self.decimals)

    def to_raw(self, value: float) -> int:
        """Inverse scaling, rounded to the nearest raw step."""
        if self.is_integer:
            return int(value)
        return round((value - self.offset) / self.scale)

    def raw_null(self) -> int:
        """The raw value meaning "not available" / "not requested": all ones."""
        return (1 << self.length) - 1


def _decimals(scale: float) -> int:
    """Decimal places of a resolution (0.005 -> 3), so values print as the unit reports them."""
    exponent = Decimal(repr(scale)).normalize().as_tuple().exponent
    assert isinstance(exponent, int)
    return max(0, -exponent)


@cache
def signal_rules(message_name: str) -> dict[str, SignalRule]:
    """Rules for every signal of one DBC message, keyed by signal name."""
    msg = database().get_message_by_name(message_name)
    rules: dict[str, SignalRule] = {}
    for sig in msg.signals:
        choices = (
            {int(k): str(v) for k, v in sig.choices.items()}
            if sig.choices and sig.length == 2
            else None
        )
        scale = float(sig.scale)
        offset = float(sig.offset)
        rules[sig.name] = SignalRule(
            name=sig.name,
            length=sig.length,
            scale=scale,
            offset=offset,
            decimals=_decimals(scale),
            minimum=None if sig.minimum is None else float(sig.minimum),
            maximum=None if sig.maximum is None else float(sig.maximum),
            unit=sig.unit or "",
            choices=choices,
            is_integer=scale == 1.0 and offset == 0.0,
        )
    return rules


def message(name: str) -> Message:
    """A DBC message by name."""
    return database().get_message_by_name(name)


class SignalExtractor:
    """Raw and physical values of one non-multiplexed DBC message, on the hot path.

    Calls cantools' own `decode_data` with the message's compiled codec, skipping the checks
    `Message.decode` repeats on every frame; falls back to `Message.decode` if a cantools
    release stops exposing the codec.
    """

    def __init__(self, message_name: str) -> None:
        self.message = message(message_name)
        self.rules = list(signal_rules(message_name).values())
        # (name, first raw value that is "not available", scale, offset, decimals, rule for the
        # cases the inline arithmetic does not cover: choices and integers)
        self._plan: list[tuple[str, int, float, float, int, SignalRule | None]] = []
        for r in self.rules:
            null_from = {16: 0xFB00, 8: 0xFB}.get(r.length, 1 << r.length)
            simple = r.choices is None and not r.is_integer
            self._plan.append(
                (r.name, null_from, r.scale, r.offset, r.decimals, None if simple else r)
            )
        codecs = getattr(self.message, "_codecs", None)
        # (the message's signals and formats, its length) for cantools' decode_data
        self._fast: tuple[Sequence[Signal | Data], Formats, int] | None = None
        if isinstance(codecs, dict) and "signals" in codecs and "formats" in codecs:
            self._fast = (codecs["signals"], codecs["formats"], self.message.length)

    def raw(self, data: bytes) -> dict[str, int]:
        """Raw values of the signals whose bits are all present in `data`."""
        if self._fast is not None:
            signals, formats, length = self._fast
            fast = decode_data(data, length, signals, formats, False, False, True, True)
            return cast(dict[str, int], fast)  # raw values (no scaling, no choices)
        values = self.message.decode(
            data, decode_choices=False, scaling=False, allow_truncated=True, allow_excess=True
        )
        return cast(dict[str, int], values)

    def physical(self, raw: dict[str, int]) -> JSONObject:
        """Every signal of the message: scaled value, choice name, or None (missing / N/A)."""
        out: JSONObject = {}
        for name, null_from, scale, offset, decimals, rule in self._plan:
            value = raw.get(name)
            if value is None or value >= null_from:
                out[name] = None
            elif rule is not None:
                out[name] = rule.to_physical(value)
            else:
                out[name] = round(value * scale + offset, decimals)
        return out
