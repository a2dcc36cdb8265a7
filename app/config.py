"""Gateway settings: environment (`EQGW_...`) over an optional TOML fleet file over defaults."""

from __future__ import annotations

import ipaddress
import os
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from contextvars import ContextVar
from pathlib import Path
from typing import Any, ClassVar, Literal
from urllib.parse import urlsplit

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator
from pydantic_settings import (
    BaseSettings,
    PydanticBaseSettingsSource,
    SettingsConfigDict,
    TomlConfigSettingsSource,
)

from eqgw.bus.config import BusConfig, check_gateway_name, parse_name
from eqgw.protocol.address_claim import (
    DEFAULT_FUNCTION,
    DEFAULT_INDUSTRY_GROUP,
    gateway_name,
    identity_number_of,
)

CONFIG_ENV_VAR = "EQGW_CONFIG"

# The TOML file of the settings being built; a context variable so that concurrent loads
# (tests) do not see each other's files.
_toml_path: ContextVar[Path | None] = ContextVar("eqgw_toml_path", default=None)


IPNetwork = ipaddress.IPv4Network | ipaddress.IPv6Network


def parse_networks(text: str) -> tuple[IPNetwork, ...]:
    """The networks of a comma-separated setting ('' = none); ValueError naming a bad one."""
    out: list[IPNetwork] = []
    for part in text.split(","):
        part = part.strip()
        if not part:
            continue
        try:
            out.append(ipaddress.ip_network(part, strict=False))
        except ValueError as exc:
            raise ValueError(f"{part!r} is not a network (e.g. 10.0.0.0/8): {exc}") from exc
    return tuple(out)


class ConfigError(Exception):
    """The configuration is invalid or its file cannot be read; the message says where."""


def check_fleet(vehicles: Sequence[VehicleConfig], buses: Sequence[BusConfig]) -> None:
    """ValueError unless the vehicles and buses make one fleet: unique vehicle ids and bus
    names, every bus on a vehicle of the fleet. The one check of a whole fleet, whether it
    comes from the fleet file or from the database (eqgw.fleet)."""
    ids = [v.id for v in vehicles]
    dupes = sorted({i for i in ids if ids.count(i) > 1})
    if dupes:
        raise ValueError(f"duplicate vehicle id(s): {', '.join(dupes)}")
    names = [b.name for b in buses]
    dupes = sorted({n for n in names if names.count(n) > 1})
    if dupes:
        raise ValueError(f"duplicate bus name(s): {', '.join(dupes)}")
    known = set(ids)
    for bus in buses:
        if bus.vehicle_id not in known:
            raise ValueError(
                f"bus {bus.name!r} refers to vehicle {bus.vehicle_id!r}, "
                "which is not in [[vehicles]]"
            )


class VehicleConfig(BaseModel):
    """A vehicle of the fleet."""

    model_config = ConfigDict(extra="forbid")

    id: str = Field(min_length=1, max_length=64, description="Stable id, e.g. 'BUS-101'")
    name: str | None = Field(default=None, max_length=200)
    depot: str | None = Field(default=None, max_length=200, description="Depot or group")

    @field_validator("id")
    @classmethod
    def _id_addressable(cls, v: str) -> str:
        # An id is a path segment of the API (/vehicles/{id}) and a column of every export.
        if v != v.strip() or "/" in v or any(ord(c) < 32 or ord(c) == 127 for c in v):
            raise ValueError(
                "a vehicle id has no '/', no control characters and no space at either end"
            )
        return v

    @field_validator("name", "depot")
    @classmethod
    def _printable(cls, v: str | None) -> str | None:
        if v is not None and any(ord(c) < 32 or ord(c) == 127 for c in v):
            raise ValueError("no control characters (newlines, tabs, NUL)")
        return v

    @property
    def display_name(self) -> str:
        return self.name or self.id


class WriterSettings(BaseModel):
    """Batching and retry of the database writer."""

    model_config = ConfigDict(extra="forbid")

    # Under light load the flush interval makes the batches; a writer that falls behind takes
    # up to this many rows per transaction, and big batches cost fewer round trips per row.
    batch_rows: int = Field(default=20_000, ge=1, description="Flush when this many rows wait")
    flush_ms: int = Field(default=500, ge=1, description="Flush at least this often")
    max_pending_rows: int = Field(
        default=1_000_000,
        ge=1,
        description="Rows held in memory while the database is away (430-530 B each, "
        "bench/held_rows.py)",
    )
    retry_initial_s: float = Field(default=0.2, gt=0)
    retry_max_s: float = Field(default=10.0, gt=0)
    # The journal (app/ingest/journal.py) keeps held rows across a restart or a kill.
    journal: bool = Field(
        default=True, description="Spill rows held during an outage, and at stop, to disk"
    )
    journal_dir: str | None = Field(
        default=None,
        description="Folder of the journal file; default: the SQLite database's folder, or "
        "the working directory on PostgreSQL",
    )
    journal_reserve_mb: float | None = Field(
        default=None,
        ge=0,
        description="Disk space kept free beside the journal (a preallocated file) for the "
        "rows held at a stop on a full disk; default: max_pending_rows x "
        "journal_row_bytes; 0: none",
    )
    journal_row_bytes: int = Field(
        default=200,
        ge=1,
        description="Journal bytes a held row may take, for the default reservation "
        "(62-86 B measured, bench/held_rows.py)",
    )
    journal_fallback_dir: str | None = Field(
        default=None,
        description="A second journal folder (another disk) for what the journal cannot "
        "take at a stop; read at every start",
    )
    spill_after_s: float = Field(
        default=3.0,
        ge=0,
        description="Database failing this long: held rows go to the journal, then every "
        "flush interval while it lasts",
    )
    write_timeout_s: float = Field(
        default=8.0,
        gt=0,
        description="A batch not committed within this counts as a failed write (the database "
        "unreachable): its rows are kept and, past spill_after_s, journaled",
    )
    # Past max_pending_rows, live ingest either refuses new rows (counted, the live view stays
    # current) or stops reading (the bus readers' own bounded queues then drop, counted).
    overflow: Literal["drop_new", "block"] = "drop_new"

    @property
    def journal_reserve_bytes(self) -> int:
        """The space the journal keeps in reserve for a stop on a full disk."""
        if self.journal_reserve_mb is not None:
            return int(self.journal_reserve_mb * 1_000_000)
        return self.max_pending_rows * self.journal_row_bytes


class DatabaseSettings(BaseModel):
    """Deadlines of every database operation (PostgreSQL; SQLite waits `busy_timeout`).

    A database that does not answer (a blackholed path: packets dropped, no reset) must cost a
    bounded wait, never a hang: the connection gives up, the operation fails like an outage.
    """

    model_config = ConfigDict(extra="forbid")

    connect_timeout_s: int = Field(
        default=3, ge=2, description="Opening a connection (libpq `connect_timeout`, at least 2)"
    )
    answer_timeout_s: float = Field(
        default=10.0,
        gt=0,
        description="A statement, commit or batch the server has not answered within this is "
        "given up and its connection closed (client side: works whatever the network does)",
    )
    statement_timeout_s: float = Field(
        default=8.0, gt=0, description="The server cancels a statement running longer"
    )
    lock_timeout_s: float = Field(
        default=5.0, gt=0, description="The server gives up waiting for a lock after this"
    )
    idle_in_transaction_s: float = Field(
        default=30.0, gt=0, description="The server ends a session idle in a transaction"
    )
    keepalive_idle_s: int = Field(default=5, ge=1, description="TCP keepalive of each connection")
    keepalive_interval_s: int = Field(default=2, ge=1)
    keepalive_count: int = Field(default=3, ge=1)
    tcp_user_timeout_s: float = Field(
        default=10.0, gt=0, description="Data unacknowledged this long breaks the connection"
    )
    pool_timeout_s: float = Field(
        default=3.0, gt=0, description="Wait for a free pooled connection at most this long"
    )


class RetentionSettings(BaseModel):
    """How long history is kept, and how pruning batches its deletes."""

    model_config = ConfigDict(extra="forbid")

    raw_days: float = Field(default=30, gt=0, description="Raw rows and raw frames")
    rollup_1m_days: float = Field(default=30, gt=0, description="1-minute rollups")
    rollup_15m_days: float = Field(default=365, gt=0, description="15-minute rollups")
    rollup_1h_days: float = Field(default=1826, gt=0, description="1-hour rollups")
    rollup_1d_days: float = Field(default=1826, gt=0, description="1-day rollups")
    rollup_days: float = Field(
        default=730,
        gt=0,
        description="Closed fault episodes, finished webhook deliveries, other rollup widths",
    )
    batch_rows: int = Field(default=5000, ge=100, description="Rows per delete transaction")
    interval_s: float = Field(default=3600, gt=0, description="Pruning period during serve")
    partitions_ahead_days: float = Field(
        default=3, gt=0, le=60, description="PostgreSQL: time partitions made this far ahead"
    )

    def rollup_days_by_width(self) -> dict[int, float]:
        """Each rollup width's retention in days, by width in seconds."""
        return {
            60: self.rollup_1m_days,
            900: self.rollup_15m_days,
            3600: self.rollup_1h_days,
            86400: self.rollup_1d_days,
        }


class ForwardIngestSettings(BaseModel):
    """Frames uploaded by forwarders (`POST /api/v1/ingest/frames`)."""

    model_config = ConfigDict(extra="forbid")

    max_future_s: float = Field(
        default=300.0,
        gt=0,
        le=86400,
        allow_inf_nan=False,
        description="Frames stamped further ahead of this gateway's clock are refused "
        "(older than retention.raw_days too)",
    )


class MonitorSettings(BaseModel):
    """Thresholds of the per-unit monitors (offline, stuck heartbeat, stale DM1)."""

    model_config = ConfigDict(extra="forbid")

    offline_after_s: float = Field(default=10.0, gt=0)
    dm1_stale_after_s: float = Field(default=5.0, gt=0)
    heartbeat_stuck_after: int = Field(
        default=3, ge=2, description="Identical heartbeats in a row that make a stuck monitor"
    )
    bus_silent_after_s: float = Field(
        default=6.0,
        gt=0,
        description="No frame of any node on a bus for this long: the bus is silent (parked)",
    )
    not_reporting_after_s: float = Field(
        default=36 * 3600.0,
        gt=0,
        description="No frame from any unit of a vehicle for this long: it is not reporting",
    )


class HubSettings(BaseModel):
    """The in-process event hub."""

    model_config = ConfigDict(extra="forbid")

    subscriber_queue: int = Field(default=10_000, ge=1)


class AlertRuleConfig(BaseModel):
    """A rule in the config file: a new rule (with `kind`), or changes to a built-in one."""

    model_config = ConfigDict(extra="forbid")

    kind: str | None = Field(default=None, description="Condition kind (eqgw.alerts.rules)")
    severity: Literal["info", "warning", "critical"] | None = None
    enabled: bool | None = None
    params: dict[str, Any] = Field(default_factory=dict, description="Merged over the defaults")
    targets: list[str] | None = None
    description: str | None = Field(default=None, max_length=2000)


class AlertSettings(BaseModel):
    """Alert rules (built-in ones overridable here) and the engine's clock."""

    model_config = ConfigDict(extra="forbid")

    enabled: bool = Field(default=True, description="Evaluate alert rules during serve")
    tick_s: float = Field(default=1.0, gt=0, description="Re-evaluation period (delays, offline)")
    rules: dict[str, AlertRuleConfig] = Field(
        default_factory=dict, description="By rule id: overrides of built-in rules, or new rules"
    )

    @model_validator(mode="after")
    def _rules_valid(self) -> AlertSettings:
        from eqgw.alerts.config import resolve_rules

        resolve_rules(self)  # raises ValueError with the rule and the reason
        return self


# A webhook claim is renewed (or its run stopped) while at least this much of it would be left
# after one more attempt: room for recording the attempt and for the gateways' clocks.
LEASE_MARGIN_S = 1.0


class DeliverySettings(BaseModel):
    """Alert delivery to webhooks: polling, timeouts and the retry schedule."""

    model_config = ConfigDict(extra="forbid")
    lease_margin_s: ClassVar[float] = LEASE_MARGIN_S

    enabled: bool = Field(default=True, description="Deliver alert events during serve")
    poll_s: float = Field(default=1.0, gt=0, description="How often the outbox is read")
    timeout_s: float = Field(default=10.0, gt=0, description="Per HTTP attempt")
    retry_initial_s: float = Field(default=5.0, gt=0, description="First retry delay")
    retry_max_s: float = Field(default=600.0, gt=0, description="Retry delays double up to this")
    give_up_after_s: float = Field(
        default=86400.0, gt=0, description="A delivery still failing after this is failed"
    )
    batch: int = Field(default=100, ge=1, description="Deliveries claimed per round")
    # PostgreSQL assigns ids before commit: an id missing while later ones are visible is a
    # transaction still committing, or one rolled back (then never filled).
    gap_wait_s: float = Field(default=5.0, ge=0, description="How long a missing event id waits")
    lease_s: float | None = Field(
        default=None,
        gt=0,
        description="How long a claim of deliveries lasts before it is renewed (default: "
        "timeout_s + 15); at least timeout_s + 2",
    )

    @model_validator(mode="after")
    def _lease_covers_an_attempt(self) -> DeliverySettings:
        if self.lease_s is not None and self.lease_s < self.timeout_s + 2 * LEASE_MARGIN_S:
            raise ValueError(
                f"delivery.lease_s must be at least timeout_s + {2 * LEASE_MARGIN_S:g} s"
            )
        return self

    @property
    def claim_lease_s(self) -> float:
        """The claim lease in force: an attempt and the margin fit in it with room to renew."""
        return self.lease_s if self.lease_s is not None else self.timeout_s + 15.0


class AddressClaimSettings(BaseModel):
    """J1939-81 address claim (PGN 60928) of the gateway's source address on every bus: on by
    default, with a NAME composed of the fields below (or given whole as `name`)."""

    model_config = ConfigDict(extra="forbid")

    enabled: bool = Field(
        default=True,
        description="Claim gateway_sa before transmitting; off only where the "
        "integrator says the bus has no address management",
    )
    name: int | None = Field(
        default=None,
        description="The whole 64-bit NAME (decimal or 0x hex text); unset: "
        "composed from the fields below",
    )
    industry_group: int = Field(default=DEFAULT_INDUSTRY_GROUP, ge=0, le=7)
    vehicle_system: int = Field(default=0, ge=0, le=127)
    vehicle_system_instance: int = Field(default=0, ge=0, le=15)
    function: int = Field(default=DEFAULT_FUNCTION, ge=0, le=255)
    function_instance: int = Field(default=0, ge=0, le=31)
    ecu_instance: int = Field(default=0, ge=0, le=7)
    manufacturer_code: int = Field(default=0, ge=0, le=2047)
    identity_number: int | None = Field(
        default=None,
        ge=0,
        le=(1 << 21) - 1,
        description="Unset: derived from each bus's name (CRC-32, 21 bits)",
    )

    _name_from_text = field_validator("name", mode="before")(parse_name)

    @model_validator(mode="after")
    def _name_valid(self) -> AddressClaimSettings:
        if self.name is not None:
            check_gateway_name(self.name, "address_claim.name")
        return self

    def name_for(self, bus: str) -> int:
        """The NAME the gateway claims its address on `bus` with."""
        if self.name is not None:
            return self.name
        ident = self.identity_number
        return gateway_name(
            identity_number_of(bus) if ident is None else ident,
            industry_group=self.industry_group,
            vehicle_system=self.vehicle_system,
            vehicle_system_instance=self.vehicle_system_instance,
            function=self.function,
            function_instance=self.function_instance,
            ecu_instance=self.ecu_instance,
            manufacturer_code=self.manufacturer_code,
        )


def _topic_prefix(value: str) -> str:
    """A topic prefix: levels without MQTT's wildcards, no empty level at either end."""
    if any(c in value for c in "+#\0"):
        raise ValueError("a topic prefix cannot hold '+', '#' or NUL")
    if value.startswith("/") or value.endswith("/") or "//" in value:
        raise ValueError("a topic prefix has no empty level (no leading, trailing or double '/')")
    return value


class TelemetrySettings(BaseModel):
    """Live values to MQTT: a retained topic per unit and per vehicle, this gateway's
    availability (a last will), Home Assistant discovery. Off unless enabled (needs
    `mqtt.host`); eqgw.notify.telemetry."""

    model_config = ConfigDict(extra="forbid")

    enabled: bool = Field(default=False, description="Publish telemetry (needs mqtt.host)")
    topic_prefix: str = Field(
        default="eqgw",
        min_length=1,
        max_length=200,
        description="Topics are <prefix>/vehicles/... and <prefix>/gateways/<gateway_id>/status",
    )
    gateway_id: str | None = Field(
        default=None,
        min_length=1,
        max_length=64,
        description="This gateway's name in its status topic; default: "
        "EQGW_CLUSTER_INSTANCE_ID when set, else the host name",
    )
    interval_s: float = Field(
        default=5.0,
        ge=0.1,
        le=3600,
        description="A unit's or vehicle's topic is published at most once per interval, "
        "with the latest values",
    )
    qos: Literal[0, 1] = Field(default=0, description="QoS of the value topics")
    max_pending: int = Field(
        default=1000,
        ge=10,
        le=100_000,
        description="Messages handed to the client and not yet sent (QoS 0) or acknowledged "
        "(QoS 1); past it, units wait for the next round (their latest values then)",
    )
    homeassistant: bool = Field(
        default=False, description="Publish Home Assistant MQTT discovery configs"
    )
    discovery_prefix: str = Field(default="homeassistant", min_length=1, max_length=200)

    _prefixes_valid = field_validator("topic_prefix", "discovery_prefix")(_topic_prefix)


class MqttSettings(BaseModel):
    """The MQTT broker alert events are published to (off while `host` is unset), and the
    telemetry published to it (off unless `telemetry.enabled`)."""

    model_config = ConfigDict(extra="forbid")

    host: str | None = Field(default=None, description="Broker host; unset: no MQTT")
    port: int = Field(default=1883, ge=1, le=65535)
    username: str | None = None
    password: str | None = None
    tls: bool = False
    client_id: str | None = Field(default=None, max_length=128, description="Default: random")
    topic_prefix: str = Field(default="eqgw/alerts", min_length=1, max_length=200)
    qos: Literal[0, 1, 2] = 1
    keepalive_s: int = Field(default=30, ge=5)
    reconnect_min_s: float = Field(default=1.0, gt=0)
    reconnect_max_s: float = Field(default=60.0, gt=0)
    publish_timeout_s: float = Field(default=10.0, gt=0, description="Wait for the broker's ack")
    telemetry: TelemetrySettings = Field(default_factory=TelemetrySettings)

    @model_validator(mode="after")
    def _telemetry_has_a_broker(self) -> MqttSettings:
        if self.telemetry.enabled and not self.host:
            raise ValueError("mqtt.telemetry.enabled needs mqtt.host (the broker)")
        return self


class SmtpSettings(BaseModel):
    """The mail server alert emails go through (webhooks of format `email`; off while `host`
    is unset)."""

    model_config = ConfigDict(extra="forbid")

    host: str | None = Field(default=None, description="SMTP server; unset: no email")
    port: int = Field(default=587, ge=1, le=65535)
    tls: Literal["starttls", "tls", "none"] = Field(
        default="starttls",
        description="starttls (port 587), tls (implicit TLS, port 465) or none (a local relay)",
    )
    username: str | None = None
    password: str | None = None
    sender: str = Field(default="eqgw@localhost", max_length=320, description="From: address")
    ca_file: str | None = Field(
        default=None, description="CA bundle the server's certificate is checked against"
    )


class FleetSettings(BaseModel):
    """How a running gateway follows the fleet (vehicles and buses) kept in the database."""

    model_config = ConfigDict(extra="forbid")

    poll_s: float = Field(
        default=1.0,
        gt=0,
        le=60,
        description="How often the fleet's version is read: a change made through another "
        "gateway or `eqgw vehicles import` is applied within this (PostgreSQL gateways also "
        "tell each other at once)",
    )


class OidcGroup(BaseModel):
    """What one value of the groups claim grants: a role, over some depots and vehicles or over
    the whole fleet (`all`), as a key's scope."""

    model_config = ConfigDict(extra="forbid")

    role: Literal["viewer", "operator", "admin"]
    depots: list[str] = Field(default_factory=list, description="The fleet file's `depot`s")
    vehicles: list[str] = Field(default_factory=list, description="Vehicle ids")
    all: bool = Field(default=False, description="The whole fleet (then no depots nor vehicles)")

    @model_validator(mode="after")
    def _scope_said(self) -> OidcGroup:
        if self.all == bool(self.depots or self.vehicles):
            raise ValueError(
                "a group grants either `all = true` (the whole fleet) or some `depots` and/or "
                "`vehicles`"
            )
        return self


# Hosts whose plain-http issuer is accepted (a provider on this machine, as in the tests).
_LOOPBACK_HOSTS = frozenset({"localhost", "127.0.0.1", "::1"})


class OidcSettings(BaseModel):
    """Single sign-on for the dashboard through an OpenID Connect provider (off while `issuer`
    is unset); the groups claim of a person's ID token decides their role and scope."""

    model_config = ConfigDict(extra="forbid")

    issuer: str | None = Field(
        default=None,
        description="The provider's issuer URL (its /.well-known/openid-configuration is read); "
        "unset: no single sign-on",
    )
    client_id: str | None = Field(default=None, max_length=500)
    client_secret: str | None = Field(
        default=None, description="Unset: a public client (PKCE alone, no client secret)"
    )
    scopes: str = Field(
        default="openid email profile",
        description="Scopes asked for (some providers need one more for the groups claim)",
    )
    groups_claim: str = Field(
        default="groups",
        min_length=1,
        description="The claim listing a person's groups (a dotted path for a nested one, "
        "e.g. realm_access.roles)",
    )
    groups: dict[str, OidcGroup] = Field(
        default_factory=dict, description="By value of the groups claim: what it grants"
    )
    session_max_age_s: float = Field(
        default=8 * 3600.0,
        gt=0,
        le=7 * 86400,
        description="How long a single sign-on session lasts; its role and scope are those "
        "of the groups at sign-in until then",
    )
    clock_skew_s: float = Field(
        default=60.0, ge=0, le=600, description="Leeway of the ID token's times (exp, iat)"
    )
    timeout_s: float = Field(default=10.0, gt=0, le=60, description="Per request to the provider")
    ca_file: str | None = Field(
        default=None, description="CA bundle the provider's certificate is checked against"
    )
    redirect_url: str | None = Field(
        default=None,
        description="The callback registered at the provider; default: EQGW_API_PUBLIC_URL "
        "(else the address the browser used) + /auth/oidc/callback",
    )
    label: str = Field(default="Sign in with SSO", min_length=1, max_length=100)

    @property
    def enabled(self) -> bool:
        """Whether single sign-on is set up."""
        return self.issuer is not None

    @model_validator(mode="after")
    def _complete(self) -> OidcSettings:
        if self.issuer is None:
            return self
        parts = urlsplit(self.issuer)
        if parts.scheme != "https" and not (
            parts.scheme == "http" and parts.hostname in _LOOPBACK_HOSTS
        ):
            raise ValueError(
                f"oidc.issuer must be an https URL (plain http only on this machine), "
                f"not {self.issuer!r}"
            )
        if not self.client_id:
            raise ValueError("oidc.client_id is required with oidc.issuer")
        if not self.groups:
            raise ValueError(
                "oidc.groups maps no group to a role: nobody could sign in (see docs/security.md)"
            )
        if "openid" not in self.scopes.split():
            raise ValueError("oidc.scopes must include openid")
        return self


class Settings(BaseSettings):
    """Everything the gateway needs to start; validated once, at start."""

    model_config = SettingsConfigDict(
        env_prefix="EQGW_",
        env_nested_delimiter="__",
        extra="forbid",
        validate_default=True,
    )

    database_url: str = "sqlite:///eqgw.db"
    # The fleet file's vehicles and buses seed a database that has no fleet yet; from then on
    # the database's fleet is the authority (eqgw.fleet). In a running gateway these two lists
    # are the database's fleet, replaced whole (never edited in place) when it changes.
    vehicles: list[VehicleConfig] = Field(default_factory=list)
    buses: list[BusConfig] = Field(default_factory=list)
    fleet: FleetSettings = Field(default_factory=FleetSettings)
    raw_archive: bool = Field(default=True, description="Archive equalizer frames as received")
    bus_open_concurrency: int = Field(
        default=16,
        ge=1,
        le=1000,
        description="Buses opening at once (TCP connect and socketcand handshake); the others "
        "wait their turn, so hundreds of buses on one server do not overflow its accept queue",
    )
    writer: WriterSettings = Field(default_factory=WriterSettings)
    db: DatabaseSettings = Field(default_factory=DatabaseSettings)
    retention: RetentionSettings = Field(default_factory=RetentionSettings)
    forward: ForwardIngestSettings = Field(default_factory=ForwardIngestSettings)
    monitor: MonitorSettings = Field(default_factory=MonitorSettings)
    hub: HubSettings = Field(default_factory=HubSettings)
    delivery: DeliverySettings = Field(default_factory=DeliverySettings)
    mqtt: MqttSettings = Field(default_factory=MqttSettings)
    smtp: SmtpSettings = Field(default_factory=SmtpSettings)
    alerts: AlertSettings = Field(default_factory=AlertSettings)
    address_claim: AddressClaimSettings = Field(default_factory=AddressClaimSettings)
    oidc: OidcSettings = Field(default_factory=OidcSettings)
    webhook_allow_networks: str = Field(
        default="",
        description="Comma-separated networks webhooks may reach although refused by default "
        "(loopback, private, link-local), e.g. '10.20.0.0/16,127.0.0.1/32'",
    )

    @classmethod
    def settings_customise_sources(
        cls,
        settings_cls: type[BaseSettings],
        init_settings: PydanticBaseSettingsSource,
        env_settings: PydanticBaseSettingsSource,
        dotenv_settings: PydanticBaseSettingsSource,
        file_secret_settings: PydanticBaseSettingsSource,
    ) -> tuple[PydanticBaseSettingsSource, ...]:
        sources: list[PydanticBaseSettingsSource] = [init_settings, env_settings]
        path = _toml_path.get()
        if path is None and os.environ.get(CONFIG_ENV_VAR):
            path = Path(os.environ[CONFIG_ENV_VAR])
        if path is not None:
            sources.append(TomlConfigSettingsSource(settings_cls, toml_file=path))
        return tuple(sources)

    @field_validator("database_url")
    @classmethod
    def _url_supported(cls, v: str) -> str:
        from eqgw.store.engine import parse_url
        from eqgw.store.errors import DatabaseUrlError

        try:
            parse_url(v)
        except DatabaseUrlError as exc:
            raise ValueError(str(exc)) from exc
        return v

    @model_validator(mode="after")
    def _fleet_consistent(self) -> Settings:
        check_fleet(self.vehicles, self.buses)
        for bus in self.buses:
            self.apply_address_claim(bus)
        return self

    def apply_address_claim(self, bus: BusConfig) -> BusConfig:
        """Give a bus the NAME to claim `gateway_sa` with: its own `address_claim_name`, else
        `[address_claim]`'s; none where the bus opts out (`address_claim = false`) or the
        claim is off (`address_claim.enabled = false`) and the bus names none."""
        if not bus.address_claim:
            bus.address_claim_name = None
        elif bus.address_claim_name is None and self.address_claim.enabled:
            bus.address_claim_name = self.address_claim.name_for(bus.name)
        return bus

    @field_validator("webhook_allow_networks")
    @classmethod
    def _networks_valid(cls, v: str) -> str:
        parse_networks(v)  # raises ValueError naming the bad entry
        return v

    def vehicle(self, vehicle_id: str) -> VehicleConfig | None:
        """The configured vehicle with this id, if any."""
        return next((v for v in self.vehicles if v.id == vehicle_id), None)


@contextmanager
def _using_toml(path: Path | None) -> Iterator[None]:
    token = _toml_path.set(path)
    try:
        yield
    finally:
        _toml_path.reset(token)


def _format_validation(exc: ValidationError, origin: str) -> str:
    lines = [f"invalid configuration ({origin}):"]
    for err in exc.errors():
        where = ".".join(str(p) for p in err["loc"]) or "(top level)"
        lines.append(f"  {where}: {err['msg']}")
    return "\n".join(lines)


def load_settings(config_path: str | Path | None = None, **overrides: Any) -> Settings:
    """Build the settings: overrides > EQGW_ environment > TOML file (`--config`/EQGW_CONFIG)."""
    raw = config_path if config_path is not None else os.environ.get(CONFIG_ENV_VAR)
    path = Path(raw) if raw else None
    if path is not None and not path.is_file():
        raise ConfigError(f"configuration file not found: {path}")
    origin = f"file {path} and EQGW_ environment" if path else "EQGW_ environment"
    try:
        with _using_toml(path):
            return Settings(**overrides)
    except ValidationError as exc:
        raise ConfigError(_format_validation(exc, origin)) from exc
    except ValueError as exc:  # tomllib.TOMLDecodeError is a ValueError
        raise ConfigError(f"cannot read {path}: {exc}") from exc
