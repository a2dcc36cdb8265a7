"""Request bodies and documented response shapes of the REST API."""

from __future__ import annotations

from typing import Any, ClassVar, Literal

from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    StrictBool,
    StrictInt,
    field_validator,
    model_validator,
)


def nul_at(data: Any, where: tuple[str, ...] = ()) -> tuple[str, ...] | None:
    """Where in parsed JSON a text (a value or a key) holds a NUL character, or None."""
    if isinstance(data, str):
        return where if "\x00" in data else None
    if isinstance(data, dict):
        for k, v in data.items():
            found = nul_at(k, (*where, str(k))) or nul_at(v, (*where, str(k)))
            if found is not None:
                return found
    elif isinstance(data, list | tuple):
        for i, v in enumerate(data):
            if isinstance(v, str | dict | list | tuple):
                found = nul_at(v, (*where, str(i)))
                if found is not None:
                    return found
    return None


class RequestBody(BaseModel):
    """A request body. PostgreSQL text cannot hold a NUL character, so one anywhere in the
    body is a 422 saying where (audited like any invalid write), never a driver error."""

    # Top-level fields not walked: ones whose text is parsed further and refused there (a
    # forwarder's frames, hex data, where a walk would cost more than the rest of validation).
    nul_unchecked: ClassVar[frozenset[str]] = frozenset()

    @model_validator(mode="before")
    @classmethod
    def _no_nul(cls, data: Any) -> Any:
        skip = cls.nul_unchecked
        if skip and isinstance(data, dict):
            where = nul_at({k: v for k, v in data.items() if k not in skip})
        else:
            where = nul_at(data)
        if where is not None:
            path = ".".join(where).replace("\x00", "\\u0000") or "body"
            raise ValueError(f"{path}: NUL characters (\\u0000) are not accepted in text")
        return data


class ErrorBody(BaseModel):
    """Every error: a stable `type` and a human `detail`."""

    type: str
    detail: str


# Row ids (keys, alerts, mutes, webhooks) are INTEGER columns: 32 bits on PostgreSQL. A larger
# number in a path or query is a 422, not a driver error (a 500).
MAX_ID = 2**31 - 1


def errors(*codes: int) -> dict[int | str, dict[str, Any]]:
    """OpenAPI `responses` entries for these error statuses."""
    return {code: {"model": ErrorBody} for code in codes}


_UNIT = Field(
    default=None, ge=0, le=253, description="The unit's source address; optional with one unit"
)
_EXPIRES = Field(
    default=None, gt=0, le=86400, description="Seconds until the command expires (default 30)"
)


class ControlCommand(RequestBody):
    """Control of one unit (PGN 65490); each field true/false, omitted = no action."""

    model_config = ConfigDict(extra="forbid")

    unit: StrictInt | None = _UNIT
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
    """A parameter write by name, e.g. `{"ov_setpoint_v": 29.5, "fault_timer_s": 10}`."""

    model_config = ConfigDict(
        extra="allow",
        json_schema_extra={"additionalProperties": {"type": ["number", "boolean"]}},
    )

    unit: StrictInt | None = _UNIT
    expires_in_s: float | None = _EXPIRES


class DeviceRequest(RequestBody):
    """Ask the unit for a message (PGN 59904)."""

    model_config = ConfigDict(extra="forbid")

    unit: StrictInt | None = _UNIT
    what: Literal["dm1", "component_id", "software_id"]
    expires_in_s: float | None = _EXPIRES


class CommandOut(BaseModel):
    """A command and where it is in its life."""

    id: str
    kind: str
    vehicle_id: str
    bus: str
    unit: int
    request: dict[str, Any] | None
    state: Literal["queued", "sending", "confirmed", "sent", "failed", "expired", "cancelled"]
    reason: str | None
    created_at: float
    updated_at: float
    expires_at: float
    first_sent_at: float | None
    last_sent_at: float | None
    sends: int
    key_name: str | None


class KeyCreate(RequestBody):
    """A new API key."""

    model_config = ConfigDict(extra="forbid")

    name: str = Field(min_length=1, max_length=200)
    role: Literal["viewer", "operator", "admin", "ingest"]

    @field_validator("name")
    @classmethod
    def _name(cls, value: str) -> str:
        from app.api.auth import check_key_name

        return check_key_name(value)


class KeyOut(BaseModel):
    """An API key as listed (never the key itself)."""

    id: int
    name: str
    role: str
    prefix: str
    created_at: float
    revoked_at: float | None
    last_used_at: float | None


class KeyCreated(KeyOut):
    """A key just created: `key` is shown this once."""

    key: str
