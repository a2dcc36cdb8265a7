"""Alert rules, pure: definitions, the built-in set, conditions with hysteresis, the delay.

A rule is a condition `kind` with its `params`, a severity and its destinations. A condition
looks at one unit's facts (latest values, status flags, open fault episodes) and gives a
`Verdict`: FIRE (beyond the firing level), CLEAR (back past the clearing level) or HOLD (in
between, or no data). `RuleState.step` turns verdicts over time into raise and clear decisions:
an alert is raised once FIRE has held for `delay_s`, and cleared once CLEAR has held for
`clear_delay_s`; HOLD keeps an open alert open (hysteresis) and resets a pending one. Nothing
here touches a database, the hub or the clock: time is an argument.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from datetime import UTC, datetime
from enum import Enum
from typing import Any

from eqgw.fleet.diagnosis import Batteries

SEVERITIES = ("info", "warning", "critical")


class Verdict(Enum):
    """What a condition says about a unit right now."""

    FIRE = "fire"
    CLEAR = "clear"
    HOLD = "hold"


class Decision(Enum):
    """What the state machine decided at a step."""

    RAISE = "raise"
    CLEAR = "clear"


@dataclass(frozen=True, slots=True)
class Facts:
    """What a condition may look at: one unit's latest values, flags and open faults."""

    latest: Mapping[str, tuple[float, Mapping[str, Any]]]
    flags: Mapping[str, Any] | None
    faults: frozenset[str]
    online: bool = True
    # The unit's vehicle (eqgw.ingest.state.vehicle_status): its state and when it was last
    # heard; `vehicle_lead`: this unit carries the vehicle's own alerts (one per vehicle).
    vehicle_state: str | None = None
    vehicle_last_heard: float | None = None
    vehicle_lead: bool = False

    def value(self, slot: str, name: str) -> float | None:
        hit = self.latest.get(slot)
        if hit is None:
            return None
        v = hit[1].get(name)
        return float(v) if isinstance(v, int | float) else None

    def flag(self, name: str) -> bool:
        return bool(self.flags) and self.flags is not None and self.flags.get(name) == "active"

    def battery_value(self, battery: str, name: str) -> float | None:
        """A battery-states value of battery `12v` or `24v` (indexes 1-4 carry the battery)."""
        for idx in (1, 2, 3, 4):
            hit = self.latest.get(f"battery_states/{idx}")
            if hit is not None and hit[1].get("battery") == battery and name in hit[1]:
                v = hit[1].get(name)
                if isinstance(v, int | float):
                    return float(v)
        return None

    def batteries(self) -> Batteries | None:
        """Battery A, battery B and B - A (`eqgw.fleet.diagnosis.Batteries`)."""
        v12, v24 = self.value("voltages", "v12"), self.value("voltages", "v24")
        if v12 is None or v24 is None:
            return None
        return Batteries.of(v12, v24)


@dataclass(frozen=True, slots=True)
class Observation:
    """A condition's verdict with the numbers it was made from and a sentence for people."""

    verdict: Verdict
    message: str = ""
    values: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True, slots=True)
class Rule:
    """An alert rule; `params` are the condition's (see CONDITIONS) plus `delay_s` and
    `clear_delay_s`."""

    id: str
    kind: str
    severity: str
    enabled: bool = True
    params: Mapping[str, Any] = field(default_factory=dict)
    targets: tuple[str, ...] = ()
    description: str | None = None
    source: str = "builtin"

    @property
    def delay_s(self) -> float:
        return float(self.params.get("delay_s", 0.0))

    @property
    def clear_delay_s(self) -> float:
        return float(self.params.get("clear_delay_s", 0.0))

    def observe(self, facts: Facts) -> Observation:
        """This rule's verdict on one unit."""
        return CONDITIONS[self.kind].evaluate(self.params, facts)

    def to_dict(self) -> dict[str, Any]:
        return {
            "id": self.id,
            "kind": self.kind,
            "severity": self.severity,
            "enabled": self.enabled,
            "params": dict(self.params),
            "targets": list(self.targets),
            "description": self.description,
            "source": self.source,
        }


# -- conditions ---------------------------------------------------------------------------


def _num(params: Mapping[str, Any], name: str) -> float:
    return float(params[name])


def _imbalance(p: Mapping[str, Any], f: Facts) -> Observation:
    ab = f.batteries()
    flagged = bool(p.get("use_flag", True)) and ("IMB" in f.faults or f.flag("imb"))
    if ab is None:
        if flagged:
            return Observation(Verdict.FIRE, "the unit reports an imbalance (IMB)", {})
        return Observation(Verdict.HOLD)
    a, b, diff = ab.a_v, ab.b_v, ab.imbalance_v
    values: dict[str, Any] = {"imbalance_v": diff, "battery_a_v": a, "battery_b_v": b}
    values |= {"v12": f.value("voltages", "v12"), "v24": f.value("voltages", "v24")}
    fire, clear = _num(p, "fire_v"), _num(p, "clear_v")
    if flagged or abs(diff) > fire:
        why = "the unit reports IMB" if flagged and abs(diff) <= fire else f"|B - A| > {fire} V"
        msg = f"batteries out of balance: B - A = {diff:+.2f} V ({why})"
        return Observation(Verdict.FIRE, msg, values)
    if abs(diff) <= clear:
        return Observation(
            Verdict.CLEAR, f"batteries back in balance: B - A = {diff:+.2f} V", values
        )
    return Observation(Verdict.HOLD, "", values)


def _voltage(direction: str) -> Callable[[Mapping[str, Any], Facts], Observation]:
    code = "UVF" if direction == "under" else "OVF"

    def evaluate(p: Mapping[str, Any], f: Facts) -> Observation:
        v24 = f.value("voltages", "v24")
        flagged = bool(p.get("use_flag", True)) and (code in f.faults or f.flag(code.lower()))
        values = {"v24": v24, "v12": f.value("voltages", "v12")}
        fire, clear = _num(p, "fire_v24"), _num(p, "clear_v24")
        word = "undervoltage" if direction == "under" else "overvoltage"
        if v24 is None:
            if flagged:
                return Observation(Verdict.FIRE, f"system {word}: the unit reports {code}", values)
            return Observation(Verdict.HOLD)
        beyond = v24 < fire if direction == "under" else v24 > fire
        back = v24 >= clear if direction == "under" else v24 <= clear
        if flagged or beyond:
            why = (
                f"the unit reports {code}"
                if flagged and not beyond
                else (f"below {fire} V" if direction == "under" else f"above {fire} V")
            )
            return Observation(Verdict.FIRE, f"system {word}: V24 {v24:.2f} V ({why})", values)
        if back:
            return Observation(Verdict.CLEAR, f"system voltage back to {v24:.2f} V", values)
        return Observation(Verdict.HOLD, "", values)

    return evaluate


def _fault(p: Mapping[str, Any], f: Facts) -> Observation:
    fault = str(p["fault"])
    label = str(p.get("label") or fault)
    if fault in f.faults:
        return Observation(Verdict.FIRE, f"{label} ({fault})", {"fault": fault})
    return Observation(Verdict.CLEAR, f"{label}: no longer reported", {"fault": fault})


def _flag(p: Mapping[str, Any], f: Facts) -> Observation:
    name = str(p["flag"])
    label = str(p.get("label") or name)
    if f.flags is None or f.flags.get(name) in (None, "error", "not_available"):
        return Observation(Verdict.HOLD)
    if f.flag(name):
        return Observation(Verdict.FIRE, f"{label} (status flag {name} active)", {"flag": name})
    return Observation(Verdict.CLEAR, f"{label}: status flag {name} inactive", {"flag": name})


def _battery_pct(metric: str) -> Callable[[Mapping[str, Any], Facts], Observation]:
    def evaluate(p: Mapping[str, Any], f: Facts) -> Observation:
        fire, clear = _num(p, "fire_pct"), _num(p, "clear_pct")
        readings = {b: f.battery_value(b, metric) for b in ("12v", "24v")}
        values = {f"{metric}_{b}_pct": v for b, v in readings.items() if v is not None}
        if not values:
            return Observation(Verdict.HOLD)
        low = {b: v for b, v in readings.items() if v is not None and v < fire}
        if low:
            worst = min(low, key=lambda b: low[b])
            msg = f"{metric.upper()} of the {worst} battery {low[worst]:.1f} % (below {fire} %)"
            return Observation(Verdict.FIRE, msg, values)
        if all(v >= clear for v in values.values()):
            return Observation(Verdict.CLEAR, f"{metric.upper()} back above {clear} %", values)
        return Observation(Verdict.HOLD, "", values)

    return evaluate


def _shutdown_risk(p: Mapping[str, Any], f: Facts) -> Observation:
    ab = f.batteries()
    v24 = f.value("voltages", "v24")
    if ab is None or v24 is None:
        return Observation(Verdict.HOLD)
    a, b = ab.a_v, ab.b_v
    values = {"battery_a_v": a, "battery_b_v": b, "v24": v24, "v12": f.value("voltages", "v12")}
    bat_fire, sys_fire = _num(p, "fire_battery_v"), _num(p, "fire_system_v")
    bat_clear, sys_clear = _num(p, "clear_battery_v"), _num(p, "clear_system_v")
    reasons = []
    if min(a, b) < bat_fire:
        which = "A" if a <= b else "B"
        reasons.append(f"battery {which} at {min(a, b):.2f} V (shuts off below 8 V)")
    if v24 < sys_fire:
        reasons.append(f"system at {v24:.2f} V (shuts off below 16 V)")
    if reasons:
        return Observation(Verdict.FIRE, "equalizer near shutdown: " + "; ".join(reasons), values)
    if min(a, b) >= bat_clear and v24 >= sys_clear:
        return Observation(Verdict.CLEAR, "voltages clear of the shutdown limits", values)
    return Observation(Verdict.HOLD, "", values)


def _not_reporting(p: Mapping[str, Any], f: Facts) -> Observation:
    if f.vehicle_state is None:
        return Observation(Verdict.HOLD)
    if f.vehicle_lead and f.vehicle_state == "not_reporting":
        heard = f.vehicle_last_heard
        when = (
            "never heard"
            if heard is None
            else "last heard " + datetime.fromtimestamp(heard, UTC).strftime("%Y-%m-%d %H:%M UTC")
        )
        return Observation(Verdict.FIRE, f"vehicle not reporting ({when})", {"last_heard": heard})
    return Observation(Verdict.CLEAR, "vehicle reporting again", {})


@dataclass(frozen=True, slots=True)
class Condition:
    """A kind of condition: its evaluation and the parameters it needs (with defaults)."""

    kind: str
    evaluate: Callable[[Mapping[str, Any], Facts], Observation]
    required: tuple[str, ...]
    description: str


CONDITIONS: dict[str, Condition] = {
    c.kind: c
    for c in (
        Condition(
            "imbalance",
            _imbalance,
            ("fire_v", "clear_v"),
            "IMB reported (`use_flag`), or |B - A| above fire_v; clears at or below clear_v",
        ),
        Condition(
            "undervoltage",
            _voltage("under"),
            ("fire_v24", "clear_v24"),
            "UVF reported (`use_flag`), or V24 below fire_v24; clears at or above clear_v24",
        ),
        Condition(
            "overvoltage",
            _voltage("over"),
            ("fire_v24", "clear_v24"),
            "OVF reported (`use_flag`), or V24 above fire_v24; clears at or below clear_v24",
        ),
        Condition(
            "fault",
            _fault,
            ("fault",),
            "a fault episode is open: a DM1 code (OVF, UVF, IMB, EQFLT, SPN<n>/FMI<m>), a "
            "status fault (EX24F, ...), OFFLINE or HEARTBEAT_STUCK",
        ),
        Condition("flag", _flag, ("flag",), "a status flag (SPEC-NOTES name) is active"),
        Condition(
            "soc_below",
            _battery_pct("soc"),
            ("fire_pct", "clear_pct"),
            "SOC of either battery below fire_pct; clears when both are at or above clear_pct",
        ),
        Condition(
            "soh_below",
            _battery_pct("soh"),
            ("fire_pct", "clear_pct"),
            "SOH of either battery below fire_pct; clears when both are at or above clear_pct",
        ),
        Condition(
            "shutdown_risk",
            _shutdown_risk,
            ("fire_battery_v", "clear_battery_v", "fire_system_v", "clear_system_v"),
            "a battery below fire_battery_v or the system below fire_system_v",
        ),
        Condition(
            "not_reporting",
            _not_reporting,
            (),
            "no frame from any unit of the vehicle for monitor.not_reporting_after_s; one "
            "alert per vehicle (on its lowest bus and SA), cleared when it is heard again",
        ),
    )
}

# Pairs (fire, clear) whose clearing level must lie on the safe side of the firing level.
_HYSTERESIS: dict[str, tuple[tuple[str, str, str], ...]] = {
    "imbalance": (("fire_v", "clear_v", "below"),),
    "undervoltage": (("fire_v24", "clear_v24", "above"),),
    "overvoltage": (("fire_v24", "clear_v24", "below"),),
    "soc_below": (("fire_pct", "clear_pct", "above"),),
    "soh_below": (("fire_pct", "clear_pct", "above"),),
    "shutdown_risk": (
        ("fire_battery_v", "clear_battery_v", "above"),
        ("fire_system_v", "clear_system_v", "above"),
    ),
}


def validate_rule(kind: str, severity: str, params: Mapping[str, Any]) -> list[str]:
    """Reasons a rule is invalid (empty when it is valid)."""
    problems: list[str] = []
    cond = CONDITIONS.get(kind)
    if cond is None:
        return [f"kind {kind!r} is unknown; use one of {', '.join(sorted(CONDITIONS))}"]
    if severity not in SEVERITIES:
        problems.append(f"severity {severity!r} is unknown; use one of {', '.join(SEVERITIES)}")
    for name in cond.required:
        if name not in params:
            problems.append(f"params.{name} is required for kind {kind}")
    for name in ("delay_s", "clear_delay_s"):
        v = params.get(name, 0)
        if not isinstance(v, int | float) or isinstance(v, bool) or not 0 <= v <= 7 * 86400:
            problems.append(f"params.{name} must be a number of seconds, 0..604800")
    for name, v in params.items():
        if name in ("fault", "flag", "label"):
            if not isinstance(v, str) or not v:
                problems.append(f"params.{name} must be a non-empty string")
        elif name == "use_flag":
            if not isinstance(v, bool):
                problems.append("params.use_flag must be true or false")
        elif not isinstance(v, int | float) or isinstance(v, bool):
            problems.append(f"params.{name} must be a number")
        elif not math.isfinite(v):
            # NaN compares false with everything: a rule with it could never fire.
            problems.append(f"params.{name} must be a finite number, not {v}")
    if problems:
        return problems
    for fire_name, clear_name, side in _HYSTERESIS.get(kind, ()):
        fire, clear = float(params[fire_name]), float(params[clear_name])
        if (side == "above" and clear < fire) or (side == "below" and clear > fire):
            problems.append(
                f"params.{clear_name} ({clear}) must be {side} or equal to "
                f"params.{fire_name} ({fire}): the hysteresis clears on the safe side"
            )
    return problems


# -- the built-in rules -------------------------------------------------------------------

# Where each default comes from is in docs/alerts.md ("Rules"): the troubleshooting table
# (B - A > 0.10 V is overload or an equalizer not functioning; shut off below 16 V system or
# 8 V on either battery), the manuals' monitor rules (offline after 10 s silent, stuck
# heartbeat) and the units' own fault timer (10 s); the simulator's default setpoints
# (UV 24.0 V, OV 30.0 V) where the manuals give only the range (20..40 V).
BUILTIN_RULES: tuple[Rule, ...] = (
    Rule(
        "imbalance",
        "imbalance",
        "warning",
        params={"fire_v": 0.10, "clear_v": 0.07, "use_flag": True, "delay_s": 30.0},
        description="Batteries out of balance: IMB, or battery B - A beyond 0.10 V for 30 s",
    ),
    Rule(
        "undervoltage",
        "undervoltage",
        "warning",
        params={"fire_v24": 24.0, "clear_v24": 24.4, "use_flag": True, "delay_s": 10.0},
        description="System undervoltage: UVF, or V24 below 24.0 V for 10 s",
    ),
    Rule(
        "overvoltage",
        "overvoltage",
        "critical",
        params={"fire_v24": 30.0, "clear_v24": 29.6, "use_flag": True, "delay_s": 10.0},
        description="System overvoltage: OVF, or V24 above 30.0 V for 10 s",
    ),
    Rule(
        "equalizer_fault",
        "fault",
        "critical",
        params={"fault": "EQFLT", "label": "equalizer fault", "delay_s": 0.0},
        description="The equalizer reports EQFLT (DM1 or status flag)",
    ),
    Rule(
        "offline",
        "fault",
        "warning",
        params={"fault": "OFFLINE", "label": "unit offline", "delay_s": 0.0},
        description="No frame from the unit for 10 s (monitor.offline_after_s) while its bus "
        "carries traffic (a unit silent with its whole bus is parked: no alert)",
    ),
    Rule(
        "not_reporting",
        "not_reporting",
        "warning",
        params={"delay_s": 0.0},
        description="No frame from the vehicle for 36 h (monitor.not_reporting_after_s)",
    ),
    Rule(
        "heartbeat_stuck",
        "fault",
        "warning",
        params={"fault": "HEARTBEAT_STUCK", "label": "monitor heartbeat stuck", "delay_s": 0.0},
        description="The heartbeat stopped alternating (monitor.heartbeat_stuck_after frames)",
    ),
    Rule(
        "jump_start_left_on",
        "flag",
        "warning",
        params={"flag": "state_can_jso", "label": "jump-start override left on", "delay_s": 600.0},
        description="Jump-start override still on after 10 minutes",
    ),
    Rule(
        "soc_low",
        "soc_below",
        "warning",
        params={"fire_pct": 40.0, "clear_pct": 45.0, "delay_s": 60.0},
        description="State of charge of either battery below 40 % for a minute (80-series)",
    ),
    Rule(
        "soh_low",
        "soh_below",
        "info",
        params={"fire_pct": 70.0, "clear_pct": 72.0, "delay_s": 300.0},
        description="State of health of either battery below 70 % (80-series)",
    ),
    Rule(
        "shutdown_risk",
        "shutdown_risk",
        "critical",
        params={
            "fire_battery_v": 8.5,
            "clear_battery_v": 9.0,
            "fire_system_v": 16.5,
            "clear_system_v": 17.0,
            "delay_s": 3.0,
        },
        description="A battery near 8 V or the system near 16 V, where the equalizer shuts off",
    ),
)


def builtin_rules() -> dict[str, Rule]:
    """The built-in rules by id."""
    return {r.id: r for r in BUILTIN_RULES}


# -- the delay and clear-delay state machine -----------------------------------------------


@dataclass(slots=True)
class RuleState:
    """One (unit, rule): whether an alert is open, and since when its verdict has held."""

    open: bool = False
    alert_id: int | None = None
    pending_since: float | None = None
    clearing_since: float | None = None

    def step(
        self, verdict: Verdict, now: float, delay_s: float, clear_delay_s: float
    ) -> Decision | None:
        """Advance by one verdict at time `now`; RAISE or CLEAR when the delay has held.

        The caller applies the decision (and sets `open` through `opened`/`closed`)."""
        if not self.open:
            self.clearing_since = None
            if verdict is not Verdict.FIRE:
                self.pending_since = None  # it did not hold: start again next time
                return None
            if self.pending_since is None or now < self.pending_since:
                self.pending_since = now
            return Decision.RAISE if now - self.pending_since >= delay_s else None
        self.pending_since = None
        if verdict is not Verdict.CLEAR:
            self.clearing_since = None
            return None
        if self.clearing_since is None or now < self.clearing_since:
            self.clearing_since = now
        return Decision.CLEAR if now - self.clearing_since >= clear_delay_s else None

    def opened(self, alert_id: int | None) -> None:
        self.open, self.alert_id = True, alert_id
        self.pending_since = self.clearing_since = None

    def closed(self) -> None:
        self.open, self.alert_id = False, None
        self.pending_since = self.clearing_since = None
