"""The manuals' troubleshooting table applied to a unit's latest readings (pure)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

# Battery B - battery A, volts: the manuals' thresholds.
STANDBY_V = 0.05
NORMAL_MAX_V = 0.10
# The unit shuts off below 16 V system or 8 V on either battery; warn a little before.
SHUTDOWN_SYSTEM_V = 16.0
SHUTDOWN_BATTERY_V = 8.0
RISK_MARGIN_V = 0.5

CONDITIONS = (
    "unknown",
    "standby",
    "normal",
    "overload",
    "equalizer_not_functioning",
    "abnormal",
    "shutdown_risk",
)

_TEXT = {
    "unknown": "no voltage reading yet",
    "standby": "batteries balanced within 0.05 V: standby",
    "normal": "B - A within 0.05..0.10 V: normal equalizing",
    "overload": "B - A above 0.10 V while running: 12 V load above the equalizer's rating",
    "equalizer_not_functioning": "B - A above 0.10 V and not running: equalizer not functioning",
    "abnormal": "battery A above battery B: suspect battery B or a 12 V load on B",
    "shutdown_risk": "system below 16 V or a battery below 8 V (or close): the unit shuts off",
}


@dataclass(frozen=True, slots=True)
class Batteries:
    """The two batteries of a 24 V system from a unit's V12 and V24 (the troubleshooting table:
    battery A = V12, battery B = V24 - V12), each value rounded once to the millivolt from the
    readings, so the fleet view, the diagnosis, the alerts and MQTT show the same numbers."""

    a_v: float
    b_v: float
    imbalance_v: float  # battery B - battery A

    @classmethod
    def of(cls, v12: float, v24: float) -> Batteries:
        return cls(round(v12, 3), round(v24 - v12, 3), round((v24 - v12) - v12, 3))


def diagnose(voltages: dict[str, Any] | None, status: dict[str, Any] | None) -> dict[str, Any]:
    """The troubleshooting row for the readings, with the numbers it was made from."""
    v12 = (voltages or {}).get("v12")
    v24 = (voltages or {}).get("v24")
    flags = status or {}
    running = flags.get("eqrn") == "active"
    shutdown_flag = flags.get("io_in_sdn") == "active"
    if v12 is None or v24 is None:
        condition = "shutdown_risk" if shutdown_flag else "unknown"
        return {
            "condition": condition,
            "text": _TEXT[condition],
            "battery_a_v": v12,
            "battery_b_v": None,
            "system_v": v24,
            "b_minus_a_v": None,
            "running": running if status else None,
            "shutdown_flag": shutdown_flag,
        }
    bat = Batteries.of(v12, v24)
    a, b, diff = bat.a_v, bat.b_v, bat.imbalance_v
    if (
        shutdown_flag
        or v24 < SHUTDOWN_SYSTEM_V + RISK_MARGIN_V
        or min(a, b) < SHUTDOWN_BATTERY_V + RISK_MARGIN_V
    ):
        condition = "shutdown_risk"
    elif diff < -STANDBY_V:
        condition = "abnormal"
    elif diff <= STANDBY_V + 1e-9:
        condition = "standby"
    elif diff <= NORMAL_MAX_V + 1e-9:
        condition = "normal"
    elif running:
        condition = "overload"
    else:
        condition = "equalizer_not_functioning"
    return {
        "condition": condition,
        "text": _TEXT[condition],
        "battery_a_v": a,
        "battery_b_v": b,
        "system_v": round(v24, 3),
        "b_minus_a_v": diff,
        "running": running if status else None,
        "shutdown_flag": shutdown_flag,
    }
