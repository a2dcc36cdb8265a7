"""Parameter writes: the manuals' ranges per series, validation with reasons, and encoding."""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from decimal import Decimal

from eqgw.protocol import dbc
from eqgw.protocol.decode import parameter_signals
from eqgw.protocol.encode import Frame, encode
from eqgw.protocol.j1939 import DEFAULT_EQUALIZER_SA

# 70-series units accept parameter indexes 0 (factory reset) and 9 only (SPEC-NOTES).
_SERIES_70_INDEXES = frozenset({0, 9})
FACTORY_RESET = "factory_reset"


@dataclass(frozen=True, slots=True)
class ParameterSpec:
    """One writable parameter: where it goes, which series take it, its range and resolution."""

    name: str
    index: int
    series: frozenset[int]
    unit: str
    minimum: float
    maximum: float
    resolution: float
    description: str


def _build() -> dict[str, ParameterSpec]:
    msg = dbc.message("parameters")
    specs: dict[str, ParameterSpec] = {}
    rules = dbc.signal_rules("parameters")
    for index in range(0, 11):
        for name in parameter_signals(index):
            rule = rules[name]
            sig = msg.get_signal_by_name(name)
            if index in _SERIES_70_INDEXES and name != "profile":
                series = frozenset({70, 80})
            else:
                series = frozenset({80})  # the reset profile number is an 80-series addition
            assert rule.minimum is not None and rule.maximum is not None
            specs[name] = ParameterSpec(
                name=name,
                index=index,
                series=series,
                unit=rule.unit,
                minimum=rule.minimum,
                maximum=rule.maximum,
                resolution=rule.scale,
                description=str(sig.comment or ""),
            )
    return specs


PARAMETERS: dict[str, ParameterSpec] = _build()


def _supported(spec_series: frozenset[int], series: int | None) -> bool:
    # A unit whose series is not learned yet may only get what both series accept.
    if series is None:
        return spec_series == frozenset({70, 80})
    return series in spec_series


def validate_parameter_write(values: Mapping[str, object], series: int | None) -> list[str]:
    """Reasons the write is refused (empty when it may be sent)."""
    reasons: list[str] = []
    if not values:
        return ["no parameter given"]
    for name, value in values.items():
        if name == FACTORY_RESET:
            if value is not True:
                reasons.append("factory_reset: must be true when given")
            continue
        spec = PARAMETERS.get(name)
        if spec is None:
            reasons.append(f"{name}: unknown parameter")
            continue
        if not _supported(spec.series, series):
            which = "an unknown series" if series is None else f"the {series}-series"
            reasons.append(f"{name}: not supported by {which} (index {spec.index})")
            continue
        if isinstance(value, bool) or not isinstance(value, int | float):
            reasons.append(f"{name}: {value!r} is not a number")
            continue
        if not math.isfinite(value):
            reasons.append(f"{name}: must be finite")
            continue
        if not spec.minimum <= value <= spec.maximum:
            unit = f" {spec.unit}" if spec.unit else ""
            reasons.append(
                f"{name}: {value}{unit} is outside {spec.minimum:g}..{spec.maximum:g}{unit}"
            )
            continue
        steps = (Decimal(repr(value)) - Decimal(repr(spec.minimum))) / Decimal(
            repr(spec.resolution)
        )
        if steps != steps.to_integral_value():
            reasons.append(
                f"{name}: {value} is not a multiple of the {spec.resolution:g} resolution"
            )
    if FACTORY_RESET in values and "profile" in values:
        reasons.append("factory_reset and profile: give one (profile implies the reset)")
    return reasons


def encode_parameter_write(
    values: Mapping[str, object],
    *,
    sa: int,
    series: int | None,
    da: int = DEFAULT_EQUALIZER_SA,
) -> list[Frame]:
    """One PGN 65491 frame per index touched, in index order; raises ValueError if invalid."""
    reasons = validate_parameter_write(values, series)
    if reasons:
        raise ValueError("; ".join(reasons))
    by_index: dict[int, dict[str, object]] = {}
    for name, value in values.items():
        if name == FACTORY_RESET:
            by_index.setdefault(0, {"index": 0})
            continue
        spec = PARAMETERS[name]
        by_index.setdefault(spec.index, {"index": spec.index})[name] = value
    frames: list[Frame] = []
    for index in sorted(by_index):
        frames += encode("parameters", by_index[index], sa=sa, da=da, series=series or 80)
    return frames
