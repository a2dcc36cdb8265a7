"""Request bodies and response shapes of the alerting endpoints."""

from __future__ import annotations

from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, JsonValue

from eqgw.alerts.rules import CONDITIONS
from eqgw.web.schemas import RequestBody, _body_schema

Severity = Literal["info", "warning", "critical"]
AlertState = Literal["active", "acknowledged", "cleared"]
_HHMM = r"^([01][0-9]|2[0-3]):[0-5][0-9]$"
MAX_MUTE_S = 366 * 86400


class AlertOut(BaseModel):
    """An alert; times are epoch seconds (null when not yet); `values` carry units in keys."""

    id: int
    vehicle_id: str
    vehicle_name: str
    bus: str
    sa: int
    rule: str
    severity: Severity
    state: AlertState
    muted: bool = Field(description="raised while a mute covered it: recorded, not delivered")
    message: str
    values: dict[str, Any]
    raised_at: float
    acknowledged_at: float | None
    acknowledged_by: str | None
    ack_comment: str | None
    cleared_at: float | None
    cleared_by: str | None = Field(description="condition, rule_disabled or rule_deleted")


class AlertList(BaseModel):
    alerts: list[AlertOut]


class AlertEventOut(BaseModel):
    """One change of an alert, as stored in `alert_events` (the delivery outbox)."""

    id: int
    alert_id: int
    kind: Literal["raised", "acknowledged", "cleared"]
    ts: float
    payload: dict[str, Any]
    muted: bool


class AlertDetail(AlertOut):
    events: list[AlertEventOut]


class Acknowledge(RequestBody):
    """Acknowledge an alert: someone has seen it and is on it."""

    model_config = ConfigDict(extra="forbid")

    comment: str | None = Field(default=None, max_length=2000)


class RuleIn(RequestBody):
    """A new alert rule. `params`: the condition's levels (see `GET /alerts/rules` `kinds`),
    plus `delay_s` (fire only if it holds this long) and `clear_delay_s`."""

    model_config = ConfigDict(extra="forbid")

    id: str = Field(pattern=r"^[a-z0-9][a-z0-9_.-]{0,63}$")
    kind: str = Field(
        max_length=32,
        description=f"one of {', '.join(sorted(CONDITIONS))}",
        json_schema_extra={"enum": list[JsonValue](sorted(CONDITIONS))},
    )
    severity: Severity
    enabled: bool = True
    params: dict[str, Any] = Field(default_factory=dict)
    targets: list[str] = Field(default_factory=list, max_length=50)
    description: str | None = Field(default=None, max_length=2000)


class RulePatch(RequestBody):
    """Changes to a rule; `params` are merged over the current ones."""

    model_config = ConfigDict(extra="forbid")

    severity: Severity | None = None
    enabled: bool | None = None
    params: dict[str, Any] | None = None
    targets: list[str] | None = Field(default=None, max_length=50)
    description: str | None = Field(default=None, max_length=2000)


class RuleOut(BaseModel):
    id: str
    kind: str
    severity: Severity
    enabled: bool
    params: dict[str, Any]
    targets: list[str]
    description: str | None
    source: str = Field(description="builtin, config or api")
    created_at: float
    updated_at: float


class RuleList(BaseModel):
    rules: list[RuleOut]
    kinds: dict[str, dict[str, Any]] = Field(description="condition kinds and their parameters")


class QuietHours(RequestBody):
    """A daily window, UTC, e.g. 22:00 to 06:00 (may wrap midnight)."""

    model_config = ConfigDict(extra="forbid")

    start: str = Field(pattern=_HHMM, alias="from")
    end: str = Field(pattern=_HHMM, alias="to")


def _one_end(schema: dict[str, Any]) -> None:
    _body_schema(schema)
    # Exactly one of the two ends, as the route checks.
    schema["oneOf"] = [
        {"required": [name], "properties": {name: {"type": "number"}}}
        for name in ("ends_at", "duration_s")
    ]


class MuteIn(RequestBody):
    """Mute a vehicle (or every vehicle) for a rule (or every rule) until an expiry: give
    exactly one of `ends_at` and `duration_s`."""

    model_config = ConfigDict(extra="forbid", json_schema_extra=_one_end)

    vehicle_id: str | None = Field(default=None, max_length=64, description="null: every vehicle")
    rule: str | None = Field(default=None, max_length=64, description="null: every rule")
    starts_at: float | None = Field(default=None, ge=0, description="default: now")
    ends_at: float | None = Field(default=None, ge=0, description="the expiry (or duration_s)")
    duration_s: float | None = Field(default=None, gt=0, le=MAX_MUTE_S)
    quiet_hours: QuietHours | None = Field(
        default=None, description="only inside this daily window until the expiry"
    )
    reason: str | None = Field(default=None, max_length=2000)


class MuteOut(BaseModel):
    id: int
    vehicle_id: str | None
    rule: str | None
    starts_at: float
    ends_at: float
    quiet_hours: dict[str, str] | None
    reason: str | None
    created_by: str | None
    created_at: float
    cancelled_at: float | None
    active: bool


class MuteList(BaseModel):
    mutes: list[MuteOut]
