"""Documented shapes of the read endpoints' bodies (fleet, health, session, audit).

The handlers render these bodies themselves (orjson, cached listings), so FastAPI does not
validate them on the way out; the schemas are what the OpenAPI document promises and what the
contract test (tests/test_api_schemathesis.py) checks every answer against.
"""

from __future__ import annotations

from typing import Any, Literal

from pydantic import BaseModel, Field

# -- fleet --------------------------------------------------------------------------------------


class FaultSummary(BaseModel):
    """An open fault of a unit, in a listing."""

    fault: str = Field(description="OVF, UVF, IMB, EQFLT, SPN<n>/FMI<m>, ...")
    state: str = Field(description="active or stale")
    occurrence_count: int | None = Field(description="the unit's DM1 occurrence count")


class ShortDiagnosis(BaseModel):
    """The troubleshooting condition of a unit and its sentence."""

    condition: str = Field(
        description="standby, normal, overload, equalizer_not_functioning, abnormal, "
        "shutdown_risk or unknown"
    )
    text: str


class Diagnosis(ShortDiagnosis):
    """The troubleshooting row with the numbers it was made from."""

    battery_a_v: float | None = None
    battery_b_v: float | None = None
    system_v: float | None = None
    b_minus_a_v: float | None = None
    running: bool | None = None
    shutdown_flag: bool | None = None


_UNIT_STATE = (
    "online; offline (silent while its bus carries traffic: the `offline` alert); parked "
    "(silent with its whole bus, ignition off: no alert)"
)
_VEHICLE_STATE = (
    "not_reporting (no unit heard for monitor.not_reporting_after_s, or never), parked (every "
    "bus of the vehicle silent), offline (a unit silent while its bus carries traffic), "
    "attention (a fault open), ok"
)


class VehicleState(BaseModel):
    """A vehicle's state and when it was last heard."""

    state: Literal["ok", "attention", "offline", "parked", "not_reporting"] = Field(
        description=_VEHICLE_STATE
    )
    last_heard: float | None = Field(
        description="its units' latest frame (epoch seconds), null when never heard"
    )
    parked_since: float | None = Field(
        description="parked: when its bus fell silent (epoch seconds)"
    )


class UnitSummary(BaseModel):
    """One unit's live summary."""

    unit: int = Field(description="the unit's J1939 source address")
    bus: str
    name: str | None = Field(
        default=None,
        description="J1939 NAME (hex) of the node holding the address, from its address "
        "claim; null when no claim was seen",
    )
    series: int | None = Field(description="70 or 80 once identified")
    model: str | None
    online: bool
    state: Literal["online", "offline", "parked"] = Field(description=_UNIT_STATE)
    last_seen: float | None = Field(description="epoch seconds")
    parked_since: float | None = Field(
        description="parked: when its bus fell silent (epoch seconds)"
    )
    v12: float | None
    v24: float | None
    imbalance_v: float | None = Field(description="(v24 - v12) - v12")
    soc_12v: float | None
    soc_24v: float | None
    soh_12v: float | None
    soh_24v: float | None
    active_faults: list[str]
    faults: list[FaultSummary]
    diagnosis: ShortDiagnosis


class VehicleSummary(VehicleState):
    """A vehicle, its state and its units."""

    id: str
    name: str | None
    depot: str | None
    online: bool = Field(description="some unit of the vehicle is online")
    units: list[UnitSummary]


class VehicleList(BaseModel):
    """The fleet."""

    vehicles: list[VehicleSummary] = Field(description="the page asked for, ordered by id")
    ts: float = Field(description="when the listing was made (epoch seconds)")
    total: int = Field(description="vehicles matching the filters, on every page")
    offset: int = Field(description="vehicles skipped before this page")
    limit: int | None = Field(description="the page size asked for; null: every vehicle")
    counts: dict[str, int] | None = Field(
        default=None,
        description="with a filter or paging: vehicles per state among those matching depot "
        "and search (the state filter aside)",
    )


class LatestValue(BaseModel):
    """The latest decoded fields of one message (slot) of a unit."""

    ts: float
    fields: dict[str, Any]


class Episode(BaseModel):
    """One continuous period of one fault on one unit."""

    fault: str
    spn: int | None = None
    fmi: int | None = None
    source: str = Field(description="dm1, status, dm1+status or monitor")
    state: str = Field(description="active, stale or closed")
    started_at: float
    last_seen_at: float
    ended_at: float | None = None
    ended_by: str | None = None
    occurrence_count: int | None = None


class StoredEpisode(Episode):
    """A fault episode from the database, with its unit."""

    id: int
    unit_id: int
    vehicle_id: str
    bus: str
    sa: int


class UnitLive(BaseModel):
    """Everything known now about one unit."""

    vehicle_id: str
    bus: str
    sa: int
    unit: int = Field(description="the source address again (the listing's name for it)")
    name: str | None = Field(
        default=None,
        description="J1939 NAME (hex) of the node holding the address, from its address "
        "claim; null when no claim was seen",
    )
    series: int | None
    model: str | None
    software_id: str | None
    first_seen: float | None
    last_seen: float | None
    online: bool
    state: Literal["online", "offline", "parked"] = Field(description=_UNIT_STATE)
    parked_since: float | None = Field(
        description="parked: when its bus fell silent (epoch seconds)"
    )
    latest: dict[str, LatestValue] = Field(description="by slot: status, voltages, ...")
    faults: list[Episode]
    status_flags: dict[str, str] = Field(description="flag name: active, inactive, ...")
    summary: UnitSummary
    diagnosis: Diagnosis


class VehicleLive(VehicleState):
    """A vehicle's live view."""

    id: str
    name: str | None
    depot: str | None
    units: list[UnitLive]


class Point(BaseModel):
    """One point of a series: a bucket's aggregate, or a raw value (bucket `raw`)."""

    ts: float = Field(description="bucket start or sample time (epoch seconds)")
    value: float | None = Field(default=None, description="raw samples only")
    count: int | None = Field(default=None, description="buckets only")
    min: float | None = None
    max: float | None = None
    avg: float | None = None


class Owner(BaseModel):
    """A period one NAME held the unit's address (the first claim seen, or a change of
    owner, to the next change)."""

    name: str = Field(description="J1939 NAME (hex)")
    from_: float = Field(alias="from", description="when it took the address (epoch seconds)")
    to: float | None = Field(description="when another NAME took it; null: holds it still")


class History(BaseModel):
    """Time series of one unit."""

    vehicle_id: str
    unit: int
    bus: str
    from_: float = Field(alias="from")
    to: float
    bucket: str = Field(description="raw, 1m, 15m, 1h or 1d")
    name: str | None = Field(
        default=None,
        description="J1939 NAME (hex) holding the address now; null when no claim was seen",
    )
    owners: list[Owner] = Field(
        default_factory=list,
        description="the NAMEs that held the address during the range, oldest first: which "
        "node each part of the series is from (empty when no claim was seen)",
    )
    series: dict[str, list[Point]] = Field(description="by field name")


class StatusChange(BaseModel):
    """The status flags after a change, and which changed."""

    ts: float
    flags: dict[str, str]
    changed: list[str]


class StatusHistory(BaseModel):
    """Status-flag changes of one unit, oldest first."""

    vehicle_id: str
    unit: int
    from_: float = Field(alias="from")
    to: float
    changes: list[StatusChange]


class FaultCount(BaseModel):
    """Per fault: episodes, how many are open, and the unit's occurrence count."""

    episodes: int
    active: int
    occurrence_count: int | None


class FaultList(BaseModel):
    """Fault episodes (newest first) and counts over all of them."""

    episodes: list[StoredEpisode]
    counts: dict[str, FaultCount]
    total: int
    truncated: bool = Field(description="more episodes than listed (counts cover all)")


# -- session, audit ------------------------------------------------------------------------------


class KeyScope(BaseModel):
    """The depots and vehicles a key is limited to."""

    groups: list[str]
    vehicles: list[str]


class PersonInfo(BaseModel):
    """The person of a single sign-on session, as the OpenID provider named them."""

    subject: str = Field(description="the provider's `sub`")
    email: str | None


class GrantInfo(BaseModel):
    """A role over some vehicles, given by one group of a person's single sign-on."""

    role: str = Field(description="viewer, operator or admin")
    scope: KeyScope | None = Field(description="null: the whole fleet")


_PERSON = "single sign-on: the person; null for a key"
_GRANTS = (
    "single sign-on: the role of each group over its vehicles (`role` is the strongest, "
    "`scope` all of them; a write needs its role over the vehicle); null for a key"
)


class Me(BaseModel):
    """The calling key."""

    key_id: int | None
    name: str
    role: str = Field(description="viewer, operator, admin or ingest")
    scope: KeyScope | None = Field(
        default=None, description="the vehicles the key reaches; null: the whole fleet"
    )
    person: PersonInfo | None = Field(default=None, description=_PERSON)
    grants: list[GrantInfo] | None = Field(default=None, description=_GRANTS)
    ends_at: float | None = Field(
        default=None, description="when the key stops working (expiry or rotation), Unix s"
    )


class SessionInfo(BaseModel):
    """A browser session: the key it resolves to and the CSRF token its writes carry."""

    key_id: int | None
    name: str
    role: str = Field(description="viewer, operator or admin")
    scope: KeyScope | None = Field(
        default=None, description="the vehicles the key reaches; null: the whole fleet"
    )
    person: PersonInfo | None = Field(default=None, description=_PERSON)
    grants: list[GrantInfo] | None = Field(default=None, description=_GRANTS)
    csrf_token: str = Field(description="send as X-CSRF-Token with every write")


class ParameterInfo(BaseModel):
    """A writable parameter with the manuals' range and unit."""

    name: str
    index: int
    series: list[int]
    unit: str
    minimum: float
    maximum: float
    resolution: float
    description: str


class ParameterList(BaseModel):
    """The writable parameters."""

    parameters: list[ParameterInfo]


class AuditEntry(BaseModel):
    """One attempt to change something: who, what, when, the outcome."""

    id: int
    ts: float
    key_id: int | None
    key_name: str | None
    role: str | None
    action: str = Field(description="e.g. command.control, key.create")
    vehicle_id: str | None
    target: str | None
    request: Any = Field(description="the request body as sent, if any")
    outcome: str = Field(description="accepted, refused, done, confirmed, ...")
    status_code: int
    detail: str | None
    command_id: str | None
    subject: str | None = Field(
        default=None, description="single sign-on: the person's subject at the OpenID provider"
    )
    email: str | None = Field(default=None, description="single sign-on: the person's email")


class AuditList(BaseModel):
    """Audit entries, newest first."""

    entries: list[AuditEntry]


# -- health -------------------------------------------------------------------------------------


class Health(BaseModel):
    """The process answers."""

    status: str


class WriterState(BaseModel):
    """The batched writer."""

    state: str
    pending_rows: int
    lag_s: float | None
    consecutive_failures: int


class DatabaseState(BaseModel):
    """Whether the database answers and takes writes."""

    ok: bool
    error: str | None = None
    writer: WriterState


class BusState(BaseModel):
    """One configured bus."""

    name: str
    state: str
    last_error: str | None


class Readiness(BaseModel):
    """Ready when the database answers and takes writes and some bus is open."""

    ready: bool
    # The details below only with a whole-fleet admin key or the metrics token (a load
    # balancer, and any key scoped to depots or vehicles, sees `ready` alone).
    database: DatabaseState | None = None
    buses: list[BusState] | None = None
    alerts: dict[str, Any] | None = Field(
        default=None, description="the alert engine's state (reported only)"
    )
    delivery: dict[str, Any] | None = Field(
        default=None, description="webhook and MQTT delivery (reported only)"
    )
    telemetry: dict[str, Any] | None = Field(
        default=None, description="MQTT telemetry, when enabled (reported only)"
    )
    cluster: dict[str, Any] | None = Field(
        default=None, description="several gateways on one PostgreSQL: who reads which bus"
    )
    fleet: dict[str, Any] | None = Field(
        default=None,
        description="the fleet's version this gateway runs (vehicles, buses, when applied)",
    )
    warm_up: dict[str, Any] | None = Field(
        default=None,
        description="the API's schemas and route tables built before ready: done, seconds",
    )
