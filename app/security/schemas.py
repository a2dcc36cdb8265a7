"""The request bodies and answers of key administration (`endpoints.py`); the answers of the
audit log (`endpoints.py`), `/me` and `/parameters` (`me.py`) and `/session` (`sessions.py`).

Those read routes render their bodies themselves, so FastAPI does not validate them on the way
out: the models are what the OpenAPI document promises, and what the contract test
(tests/test_api_schemathesis.py) checks every answer against.
"""

from __future__ import annotations

from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, StrictBool, field_validator, model_validator

from eqgw.web.schemas import RequestBody

ScopeItem = Annotated[str, Field(min_length=1, max_length=200)]
# A key's expiry: at most ten years ahead (a float beyond that is a typo, not a plan).
MAX_KEY_LIFE_S = 10 * 365 * 86400.0
# ... and at least a minute ahead: a key that ends before its holder can use it locks them out.
MIN_KEY_LIFE_S = 60.0
# A rotation's overlap: the old key works at most 30 days more.
MAX_OVERLAP_S = 30 * 86400.0


class KeyScope(BaseModel):
    """The depots (the fleet file's `depot`) and vehicles a key may see and command; or
    `{"all": true}`, the whole fleet, said explicitly."""

    model_config = ConfigDict(extra="forbid")

    groups: list[ScopeItem] = Field(default=[], max_length=1000, description="Depots")
    vehicles: list[ScopeItem] = Field(default=[], max_length=10000, description="Vehicle ids")
    all: StrictBool = Field(
        default=False,
        description="true: every vehicle (alone, without groups or vehicles). For an ingest "
        "key, one leaked forwarder key then uploads for any vehicle",
    )

    @model_validator(mode="after")
    def _some(self) -> KeyScope:
        if self.all and (self.groups or self.vehicles):
            raise ValueError('{"all": true} is the whole fleet: give no groups or vehicles')
        if not self.all and not self.groups and not self.vehicles:
            raise ValueError(
                'a scope names at least one depot (groups) or vehicle, or is {"all": true}'
            )
        return self


class KeyExpiry(RequestBody):
    """An optional expiry: `expires_at` (epoch s) or `expires_in_s`, not both; at least a
    minute ahead (an expiry that ends a key before its holder can use it locks them out)."""

    # Strict numbers: `true`, `"3600"` or `null` are refused, never read as 1 or 3600.
    expires_at: float | None = Field(
        default=None,
        strict=True,
        allow_inf_nan=False,
        description="Epoch seconds, at least a minute ahead and at most ten years",
    )
    expires_in_s: float | None = Field(
        default=None,
        strict=True,
        ge=MIN_KEY_LIFE_S,
        le=MAX_KEY_LIFE_S,
        allow_inf_nan=False,
        description="Seconds from now: at least 60, at most ten years",
    )

    @model_validator(mode="after")
    def _one(self) -> KeyExpiry:
        if self.expires_at is not None and self.expires_in_s is not None:
            raise ValueError("give expires_at or expires_in_s, not both")
        return self

    def expiry(self, now: float) -> float | None:
        """The expiry as epoch seconds (None: never); ValueError when not in the future."""
        if self.expires_in_s is not None:
            return now + self.expires_in_s
        at = self.expires_at
        if at is not None and not now + MIN_KEY_LIFE_S <= at <= now + MAX_KEY_LIFE_S:
            raise ValueError(
                "expires_at must be at least a minute ahead (and at most ten years); "
                f"{at!r} is {at - now:.0f} s from now"
            )
        return self.expires_at


_NOT_CONTROL = "\\x00-\\x1f\\x7f-\\x9f"


KEY_NAME_PATTERN = f"^[^{_NOT_CONTROL}]*[^\\s{_NOT_CONTROL}][^{_NOT_CONTROL}]*$"


class KeyCreate(KeyExpiry):
    """A new API key."""

    model_config = ConfigDict(extra="forbid")

    name: str = Field(
        min_length=1,
        max_length=200,
        # Declared (check_key_name decides, saying why): no control characters, and
        # something besides spaces.
        json_schema_extra={"pattern": KEY_NAME_PATTERN},
    )
    role: Literal["viewer", "operator", "admin", "ingest"]
    scope: KeyScope | Literal["all"] | None = Field(
        default=None,
        description='`{"all": true}` or `all` (the whole fleet), or depots and vehicles; '
        "omitted: the creating key's own scope. An ingest key's scope is the vehicles it may "
        "upload for: it needs one, or the whole fleet said explicitly (a relay's key)",
    )

    @field_validator("name")
    @classmethod
    def _name(cls, value: str) -> str:
        from eqgw.security.keys import check_key_name

        return check_key_name(value)


class KeyRotate(KeyExpiry):
    """Rotation of a key: a new key like it, the old one ending after `overlap_s`."""

    model_config = ConfigDict(extra="forbid")

    overlap_s: float = Field(
        default=86400.0,
        strict=True,
        ge=0,
        le=MAX_OVERLAP_S,
        allow_inf_nan=False,
        description="How long the old key keeps working (0: revoked at once)",
    )
    scope: KeyScope | None = Field(
        default=None,
        description="A narrower scope for the new key (omitted: the old key's); never wider",
    )


class KeyOut(BaseModel):
    """An API key as listed (never the key itself)."""

    id: int
    name: str
    role: str
    prefix: str
    created_at: float
    revoked_at: float | None = Field(description="Revoked from then on (may be ahead: rotation)")
    last_used_at: float | None = Field(description="Recorded within about 10 s of a use")
    expires_at: float | None
    scope: dict[str, list[str]] | None = Field(description="null: the whole fleet")
    lineage: int = Field(description="The first key of its rotations (its own id if none)")
    active: bool


class KeyCreated(KeyOut):
    """A key just created: `key` is shown this once."""

    key: str


class KeyRotated(KeyCreated):
    """A rotation's new key (shown this once) and when the old one stops working."""

    replaces: int
    old_key_ends_at: float


# -- the answers of /me, /session, /parameters and the audit log ----------------------------------


class ScopeOut(BaseModel):
    """The depots and vehicles a key is limited to."""

    # Named `KeyScope` in the OpenAPI document, as it always was: beside the request bodies'
    # `KeyScope` above it is the component `KeyScope-Output`, that one `KeyScope-Input`
    # (pydantic names a component after the class's qualified name, the title after its name;
    # a client generated from the document keeps its types).
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
