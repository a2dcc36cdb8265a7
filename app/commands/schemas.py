"""The command routes' bodies (control, parameter writes, requests) and their answer."""

from __future__ import annotations

from typing import Annotated, Any, Literal

from pydantic import BaseModel, BeforeValidator, ConfigDict, Field, StrictBool, StrictInt

from eqgw.web.schemas import RequestBody

_UNIT = Field(default=None, description="The unit's source address; optional with one unit")


def _whole(value: Any) -> Any:
    """A whole float (`85.0`, an integer to JSON Schema) as the int it is; anything else as
    given (booleans, fractions and strings are then refused by the strict int)."""
    return int(value) if isinstance(value, float) and value.is_integer() else value


# A unit's source address: a strict integer that takes `85.0` too (JSON Schema's `integer`
# holds it), never `true` or `"85"`.
UnitSa = Annotated[StrictInt, Field(ge=0, le=253), BeforeValidator(_whole)]
_ALL_UNITS = Field(
    default=None,
    description="Control and parameter frames are broadcasts: every equalizer on the bus acts "
    "on them. On a bus with several units, true is required (the write reaches them all)",
)
_EXPIRES = Field(
    default=None, gt=0, le=86400, description="Seconds until the command expires (default 30)"
)


class ControlCommand(RequestBody):
    """Control (PGN 65490, a broadcast: every unit on the bus acts on it); each field
    true/false, omitted = no action. `unit` picks the bus."""

    model_config = ConfigDict(extra="forbid")

    unit: UnitSa | None = _UNIT
    all_units: StrictBool | None = _ALL_UNITS
    # Strict: true or false only (not 1, "off" or "yes", which lax parsing would turn into a
    # command nobody meant to send).
    jump_start_override: StrictBool | None = None
    can_onoff_enable: StrictBool | None = None
    equalizer_on: StrictBool | None = Field(
        default=None, description="Works only while CAN on/off is enabled"
    )
    smart_sensor_messages: StrictBool | None = Field(default=None, description="70-series only")
    expires_in_s: float | None = _EXPIRES


class ParameterWrite(RequestBody):
    """A parameter write by name, e.g. `{"ov_setpoint_v": 29.5, "fault_timer_s": 10}` (PGN
    65491, a broadcast: every unit on the bus applies it). `unit` picks the bus."""

    model_config = ConfigDict(
        extra="allow",
        json_schema_extra={"additionalProperties": {"type": ["number", "boolean"]}},
    )

    unit: UnitSa | None = _UNIT
    all_units: StrictBool | None = _ALL_UNITS
    expires_in_s: float | None = _EXPIRES


class DeviceRequest(RequestBody):
    """Ask the unit for a message (PGN 59904)."""

    model_config = ConfigDict(extra="forbid")

    unit: UnitSa | None = _UNIT
    what: Literal["dm1", "component_id", "software_id"]
    expires_in_s: float | None = _EXPIRES


class AffectedUnit(BaseModel):
    """A unit a command reaches."""

    sa: int
    series: int | None


class CommandOut(BaseModel):
    """A command and where it is in its life."""

    id: str
    kind: str
    vehicle_id: str
    bus: str
    unit: int
    affected_units: list[AffectedUnit] = Field(
        description="Every unit the command reaches: all those known on the bus for control "
        "and parameter writes (broadcasts), the addressed one for a request"
    )
    request: dict[str, Any] | None
    state: Literal[
        "queued",
        "sending",
        "confirmed",
        "sent",
        "unconfirmed",
        "refused",
        "failed",
        "expired",
        "cancelled",
    ] = Field(
        description="unconfirmed: frames were handed to the interface but nothing confirmed "
        "them; the command may still take effect. refused: a unit answered with a J1939 NACK "
        "or 'access denied' (the reason quotes it). failed, expired: no frame left the gateway."
    )
    reason: str | None
    created_at: float
    updated_at: float
    expires_at: float
    first_sent_at: float | None
    last_sent_at: float | None
    sends: int
    key_name: str | None
