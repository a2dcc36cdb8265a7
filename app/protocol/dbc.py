"""The shipped DBC, loaded once with cantools, and the per-signal rules a DBC cannot express."""

from __future__ import annotations

from dataclasses import dataclass
from decimal import Decimal
from functools import cache
from importlib import resources
from typing import Any

import cantools
from cantools.database.can import Database, Message

DBC_RESOURCE = "vanner_equalizer.dbc"


def dbc_text() -> str:
    """The DBC file's text, as shipped in the package."""
    return resources.files("app.protocol").joinpath(DBC_RESOURCE).read_text(encoding="utf-8")


@cache
def database() -> Database:
    """The equalizer database (parsed once per process)."""
    db = cantools.database.load_string(dbc_text(), database_format="dbc", strict=True)
    assert isinstance(db, Database)
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

    def to_physical(self, raw: int) -> Any:
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
