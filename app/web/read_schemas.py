"""Documented shapes of the read endpoints' bodies (fleet, health, session, audit).

The handlers render these bodies themselves (orjson, cached listings), so FastAPI does not
validate them on the way out; the schemas are what the OpenAPI document promises and what the
contract test (tests/test_api_schemathesis.py) checks every answer against.
"""

from __future__ import annotations

from typing import Any

from pydantic import BaseModel, ConfigDict, Field

# -- session, audit ------------------------------------------------------------------------------


class ScopeOut(BaseModel):
    """The depots and vehicles a key is limited to."""

    # Named `KeyScope` in the OpenAPI document, as it always was: beside the request bodies'
    # `eqgw.security.schemas.KeyScope` it is the component `KeyScope-Output`, that one
    # `KeyScope-Input` (pydantic names a component after the class's qualified name, the
    # title after its name; a client generated from the document keeps its types).
    __qualname__ = "KeyScope"
    model_config = ConfigDict(title="KeyScope")

    groups: list[str]
    vehicles: list[str]


class PersonInfo(BaseModel):
    """The person of a single sign-on session, as the OpenID provider named them."""

    subject: str = Field(description="the provider's `sub`")
    email: str | None


class GrantInfo(BaseModel):
    """A role over some vehicles, given by one group of a person's single sign-on."""

    role: str = Field(description="viewer, operator or admin")
    scope: ScopeOut | None = Field(description="null: the whole fleet")


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
    scope: ScopeOut | None = Field(
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
    scope: ScopeOut | None = Field(
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
