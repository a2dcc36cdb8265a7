"""SQLAlchemy models of the history: fleet, units, time series, faults, rollups, raw frames."""

from __future__ import annotations

from typing import TYPE_CHECKING, TypeAlias

from sqlalchemy import (
    JSON,
    BigInteger,
    Boolean,
    Column,
    Double,
    ForeignKey,
    Index,
    Integer,
    LargeBinary,
    MetaData,
    SmallInteger,
    String,
    Table,
    UniqueConstraint,
    text,
)
from sqlalchemy.dialects.postgresql import JSONB
from sqlalchemy.orm import DeclarativeBase, Mapped, mapped_column

if TYPE_CHECKING:
    from sqlalchemy.sql.base import ReadOnlyColumnCollection

# Stable constraint names on both engines, so later migrations can refer to them by name.
NAMING_CONVENTION = {
    "ix": "ix_%(column_0_N_label)s",
    "uq": "uq_%(table_name)s_%(column_0_N_name)s",
    "ck": "ck_%(table_name)s_%(constraint_name)s",
    "fk": "fk_%(table_name)s_%(column_0_name)s_%(referred_table_name)s",
    "pk": "pk_%(table_name)s",
}

# The Python type of a JSON object column. SQLAlchemy evaluates the models' annotations when
# it maps them, and JSONObject, recursive, is a string it cannot evaluate: at run time the
# annotation says `dict` (the column's type is JsonType either way).
if TYPE_CHECKING:
    from eqgw.jsontypes import JSONObject

    JSONDict: TypeAlias = JSONObject
else:
    JSONDict = dict

# JSONB on PostgreSQL (compact, indexable), TEXT-backed JSON on SQLite.
JsonType = JSON().with_variant(JSONB(), "postgresql")

# Time-series tables carry unit_id without a foreign key: the writer takes ids from `units`
# itself, and a per-row FK check is a large share of bulk-insert cost on PostgreSQL.
# Big append-only tables are clustered on their natural key on SQLite (WITHOUT ROWID): the
# primary key is the table, so the idempotency key costs no second index.
_CLUSTERED: dict[str, bool] = {"sqlite_with_rowid": False}

metadata = MetaData(naming_convention=NAMING_CONVENTION)


class Base(DeclarativeBase):
    """Declarative base sharing the naming-convention metadata."""

    metadata = metadata


# A `Table` with its columns' values typed `object`, not the default Any: what a function
# taking any of the tables names, with no Any written (every `Table` is one).
CoreTable: TypeAlias = "Table[ReadOnlyColumnCollection[str, Column[object]]]"


def table_of(model: type[Base]) -> Table:  # type: ignore[explicit-any]  # see the docstring
    """A model's Core table, typed (`Model.__table__` is typed as a `FromClause`), for the
    queries that are written in SQLAlchemy Core.

    The one place the tables' columns are typed Any (a bare `Table`: SQLAlchemy 2.1's type
    argument defaults to columns of Any, which mypy counts as an Any written here): the
    queries on a model's table read its values as the types they hold. A function taking any
    of the tables names a `CoreTable` instead, and every `Table` is one. Returning a
    `CoreTable` here would type every value read through these tables `object`, to be cast
    back at each query."""
    table = model.__table__
    if not isinstance(table, Table):  # pragma: no cover - every model here maps one table
        raise TypeError(f"{model.__name__} maps no single table")
    return table


class Vehicle(Base):
    """A vehicle of the fleet (managed in the database, seeded from the fleet file, or created
    by a replay or a forwarder). A deleted vehicle is retired, not removed: its history stays,
    and creating its id again brings it back."""

    __tablename__ = "vehicles"

    id: Mapped[str] = mapped_column(String(64), primary_key=True)
    name: Mapped[str] = mapped_column(String(200))
    depot: Mapped[str | None] = mapped_column(String(200))
    retired_at: Mapped[float | None] = mapped_column(Double)


class Unit(Base):
    """One equalizer, identified by (bus, source address)."""

    __tablename__ = "units"
    __table_args__ = (UniqueConstraint("bus", "sa"),)

    id: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=True)
    vehicle_id: Mapped[str] = mapped_column(ForeignKey("vehicles.id"), index=True)
    bus: Mapped[str] = mapped_column(String(200))
    sa: Mapped[int] = mapped_column(Integer)
    series: Mapped[int | None] = mapped_column(Integer)
    model: Mapped[str | None] = mapped_column(String(64), doc="Component ID text, e.g. EQ8001")
    software_id: Mapped[str | None] = mapped_column(String(64))
    first_seen: Mapped[float | None] = mapped_column(Double)
    last_seen: Mapped[float | None] = mapped_column(Double)
    # The J1939 NAME (hex text, "0x10FF000000001267": 64 bits do not fit PostgreSQL's signed
    # BIGINT) of the node holding the address, from its address claim; NULL: no claim seen.
    name: Mapped[str | None] = mapped_column(String(18))


class UnitOwner(Base):
    """Who held a unit's address from when: one row per NAME taking it (the first claim seen,
    then each change of owner). A period ends where the next one starts."""

    __tablename__ = "unit_owners"

    unit_id: Mapped[int] = mapped_column(ForeignKey("units.id"), primary_key=True)
    since: Mapped[float] = mapped_column(Double, primary_key=True)
    name: Mapped[str] = mapped_column(String(18))


class Measurement(Base):
    """PGN 65494: battery voltages and currents (currents are null on the 70-series)."""

    __tablename__ = "measurements"
    __table_args__ = _CLUSTERED

    unit_id: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=False)
    ts: Mapped[float] = mapped_column(Double, primary_key=True)
    v12: Mapped[float | None] = mapped_column(Double)
    v24: Mapped[float | None] = mapped_column(Double)
    i12: Mapped[float | None] = mapped_column(Double)
    i24: Mapped[float | None] = mapped_column(Double)


class BatteryState(Base):
    """PGN 65497, one row per record; the columns a record's index does not carry stay null."""

    __tablename__ = "battery_states"
    __table_args__ = _CLUSTERED

    unit_id: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=False)
    ts: Mapped[float] = mapped_column(Double, primary_key=True)
    idx: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=False)
    battery: Mapped[str | None] = mapped_column(String(8))
    soc: Mapped[float | None] = mapped_column(Double)
    soc_achievable: Mapped[float | None] = mapped_column(Double)
    soh: Mapped[float | None] = mapped_column(Double)
    dod: Mapped[float | None] = mapped_column(Double)
    runtime_min: Mapped[float | None] = mapped_column(Double)
    runtime_temp_adj_min: Mapped[float | None] = mapped_column(Double)
    major_12v: Mapped[int | None] = mapped_column(Integer)
    minor_12v: Mapped[int | None] = mapped_column(Integer)
    major_24v: Mapped[int | None] = mapped_column(Integer)
    minor_24v: Mapped[int | None] = mapped_column(Integer)
    temperature_c: Mapped[float | None] = mapped_column(Double)
    # The manuals' temperature scale is doubtful: keep the raw value to rescale later.
    temperature_raw: Mapped[int | None] = mapped_column(Integer)


class StatusChange(Base):
    """PGN 65492 status flags, stored only when some flag differs from the previous frame."""

    __tablename__ = "status_changes"
    __table_args__ = _CLUSTERED

    unit_id: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=False)
    ts: Mapped[float] = mapped_column(Double, primary_key=True)
    flags: Mapped[dict[str, str]] = mapped_column(JsonType)
    changed: Mapped[list[str]] = mapped_column(JsonType)


class Dm1Snapshot(Base):
    """A DM1 (lamps and DTC list), stored when its content changes."""

    __tablename__ = "dm1_snapshots"
    __table_args__ = _CLUSTERED

    unit_id: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=False)
    ts: Mapped[float] = mapped_column(Double, primary_key=True)
    lamps: Mapped[dict[str, int]] = mapped_column(JsonType)
    dtcs: Mapped[list[JSONDict]] = mapped_column(JsonType)


class Message(Base):
    """Rare records kept whole: component/software id, control, parameters, requests."""

    __tablename__ = "messages"
    __table_args__ = _CLUSTERED

    unit_id: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=False)
    ts: Mapped[float] = mapped_column(Double, primary_key=True)
    name: Mapped[str] = mapped_column(String(32), primary_key=True)
    idx: Mapped[int] = mapped_column(Integer, primary_key=True, doc="parameter index, else 0")
    fields: Mapped[JSONDict] = mapped_column(JsonType)


class FaultEpisode(Base):
    """One continuous period of one fault on one unit: the single source of fault truth."""

    __tablename__ = "fault_episodes"
    __table_args__ = (
        UniqueConstraint("unit_id", "fault", "started_at"),
        Index(None, "state"),
    )

    id: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=True)
    unit_id: Mapped[int] = mapped_column(ForeignKey("units.id"))
    fault: Mapped[str] = mapped_column(String(64), doc="OVF, UVF, IMB, EQFLT, SPN<n>/FMI<m>, ...")
    spn: Mapped[int | None] = mapped_column(Integer)
    fmi: Mapped[int | None] = mapped_column(Integer)
    source: Mapped[str] = mapped_column(String(32), doc="dm1, status, dm1+status or monitor")
    state: Mapped[str] = mapped_column(String(16), doc="active, stale or closed")
    started_at: Mapped[float] = mapped_column(Double)
    last_seen_at: Mapped[float] = mapped_column(Double)
    ended_at: Mapped[float | None] = mapped_column(Double)
    ended_by: Mapped[str | None] = mapped_column(String(32))
    occurrence_count: Mapped[int | None] = mapped_column(
        Integer, doc="the unit's own DM1 occurrence count, latest seen"
    )


# The metrics rolled up: the measurement columns, and the battery-state fields named after
# their battery (soc_12v; unsuffixed for a record of no battery), temperature_c as it is.
MEASUREMENT_METRICS = ("v12", "v24", "i12", "i24")
BATTERY_METRICS = ("soc", "soc_achievable", "soh", "dod", "temperature_c")
ROLLUP_METRICS: tuple[str, ...] = (
    *MEASUREMENT_METRICS,
    *(
        f"{m}_{b}" if b else m
        for m in BATTERY_METRICS
        if m != "temperature_c"
        for b in ("12v", "24v", "")
    ),
    "temperature_c",
)
# A metric's columns in `rollups`: (count, sum, min, max).
ROLLUP_PARTS = ("n", "sum", "min", "max")


def rollup_columns(metric: str) -> tuple[str, str, str, str]:
    """The (count, sum, min, max) columns of `metric` in `rollups`."""
    return (f"{metric}_n", f"{metric}_sum", f"{metric}_min", f"{metric}_max")


def _rollup_table() -> CoreTable:
    """`rollups`: one row per unit, bucket width and bucket, with every metric's mergeable
    aggregate (count, sum, min, max) in columns of its own, null where the bucket has no
    value of the metric. A row per metric cost about 80 bytes of tuple header, key and index
    entry for 32 bytes of aggregate on PostgreSQL; a row per bucket shares them among the
    metrics, and a metric without values costs one bit of the null bitmap. The counts come
    first, together: the doubles after them need no padding."""
    counts = [Column(rollup_columns(m)[0], Integer) for m in ROLLUP_METRICS]
    values = [Column(name, Double) for m in ROLLUP_METRICS for name in rollup_columns(m)[1:]]
    return Table(
        "rollups",
        metadata,
        Column("unit_id", Integer, primary_key=True, autoincrement=False),
        Column("bucket_s", Integer, primary_key=True, autoincrement=False),
        Column("bucket_ts", Double, primary_key=True),
        *counts,
        *values,
        sqlite_with_rowid=_CLUSTERED["sqlite_with_rowid"],
    )


class Rollup(Base):
    """Mergeable aggregates (count, sum, min, max) of every metric over one time bucket."""

    __table__ = _rollup_table()


class RollupDeletion(Base):
    """Per unit, how many times rollups were deleted (by the retention), so that a reader
    holding rollups (eqgw.store.history_cache) can tell a bucket deleted and made again from
    one never touched. Bumped in the transaction of each deletion."""

    __tablename__ = "rollup_deletions"

    unit_id: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=False)
    generation: Mapped[int] = mapped_column(BigInteger)
    last_at: Mapped[float] = mapped_column(Double)


class LiveState(Base):
    """Latest record of each kind per unit, persisted so a restart starts from it."""

    __tablename__ = "live_state"

    unit_id: Mapped[int] = mapped_column(ForeignKey("units.id"), primary_key=True)
    name: Mapped[str] = mapped_column(String(32), primary_key=True)
    ts: Mapped[float] = mapped_column(Double)
    fields: Mapped[JSONDict] = mapped_column(JsonType)


class RawBlock(Base):
    """A unit's archived equalizer frames of one minute, packed and compressed
    (eqgw.store.archive), so history can be re-decoded when an erratum is corrected."""

    __tablename__ = "raw_blocks"

    unit_id: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=False)
    # The block's start, a multiple of eqgw.store.archive.BLOCK_S: it holds start <= ts < end.
    ts: Mapped[float] = mapped_column(Double, primary_key=True)
    frames: Mapped[int] = mapped_column(Integer)
    data: Mapped[bytes] = mapped_column(LargeBinary)


class RawRecent(Base):
    """Archived frames of the minutes not packed into `raw_blocks` yet, one row each."""

    __tablename__ = "raw_recent"
    __table_args__ = _CLUSTERED

    unit_id: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=False)
    ts: Mapped[float] = mapped_column(Double, primary_key=True)
    # The identifier with SocketCAN's flags (eqgw.store.archive.word_of): 0x80000000 extended.
    can_id: Mapped[int] = mapped_column(BigInteger, primary_key=True)
    # The frame's place among the unit's frames with this id and timestamp (0, 1, ...), in
    # the order received: every frame is kept, and a replay of the same log adds nothing.
    seq: Mapped[int] = mapped_column(
        SmallInteger, primary_key=True, autoincrement=False, server_default=text("0")
    )
    data: Mapped[bytes] = mapped_column(LargeBinary)


class MeasurementBlock(Base):
    """A unit's `measurements` of one hour, packed and compressed (eqgw.store.packed)."""

    __tablename__ = "measurement_blocks"

    unit_id: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=False)
    # The block's start, a multiple of eqgw.store.packed.BLOCK_S: it holds start <= ts < end.
    ts: Mapped[float] = mapped_column(Double, primary_key=True)
    samples: Mapped[int] = mapped_column(Integer)
    data: Mapped[bytes] = mapped_column(LargeBinary)


class BatteryBlock(Base):
    """A unit's `battery_states` of one hour, packed and compressed (eqgw.store.packed)."""

    __tablename__ = "battery_blocks"

    unit_id: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=False)
    ts: Mapped[float] = mapped_column(Double, primary_key=True)
    samples: Mapped[int] = mapped_column(Integer)
    data: Mapped[bytes] = mapped_column(LargeBinary)


# Tables pruned by the raw retention; rollups have their own, longer retention.
RAW_TABLES: tuple[CoreTable, ...] = tuple(
    map(
        table_of,
        (
            Measurement,
            BatteryState,
            StatusChange,
            Dm1Snapshot,
            Message,
            RawBlock,
            RawRecent,
            MeasurementBlock,
            BatteryBlock,
        ),
    )
)


def all_metadata() -> MetaData:
    """The metadata with every model module of eqgw.store and the domain packages imported
    (`*models.py`): later layers add tables in their own modules, and Alembic must see them
    all."""
    import importlib
    import pkgutil

    import eqgw.fleet as fleet_pkg
    import eqgw.store as store_pkg

    # The domain packages that own tables of their own.
    for pkg in (store_pkg, fleet_pkg):
        for mod in pkgutil.iter_modules(pkg.__path__):
            if mod.name.endswith("models"):
                importlib.import_module(f"{pkg.__name__}.{mod.name}")
    return metadata


# --- Alerting (issue 7, part A): rules, alerts, mutes and the alert_events outbox ----------


class AlertRule(Base):
    """An alert rule: a condition (`kind` with its `params`), a severity and its destinations."""

    __tablename__ = "alert_rules"

    id: Mapped[str] = mapped_column(String(64), primary_key=True, doc="e.g. imbalance")
    kind: Mapped[str] = mapped_column(String(32), doc="the condition evaluated (eqgw.alerts.rules)")
    severity: Mapped[str] = mapped_column(String(16), doc="info, warning or critical")
    enabled: Mapped[bool] = mapped_column(Boolean)
    params: Mapped[JSONDict] = mapped_column(JsonType, doc="thresholds, hysteresis, delay")
    targets: Mapped[list[str]] = mapped_column(JsonType, doc="where it goes: webhook/MQTT names")
    description: Mapped[str | None] = mapped_column(String(2000))
    source: Mapped[str] = mapped_column(
        String(16), doc="builtin, config or api (an api edit is no longer overwritten at start)"
    )
    created_at: Mapped[float] = mapped_column(Double)
    updated_at: Mapped[float] = mapped_column(Double)


class Alert(Base):
    """One alert of one rule on one unit, from raised to cleared; at most one open per pair."""

    __tablename__ = "alerts"
    __table_args__ = (
        # At most one open (not cleared) alert per (unit, rule), whoever writes it.
        Index(
            "ux_alerts_open_unit_rule",
            "bus",
            "sa",
            "rule",
            unique=True,
            sqlite_where=text("cleared_at IS NULL"),
            postgresql_where=text("cleared_at IS NULL"),
        ),
        Index(None, "raised_at"),
        Index(None, "vehicle_id", "raised_at"),
        Index(None, "state"),
    )

    id: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=True)
    vehicle_id: Mapped[str] = mapped_column(String(64))
    bus: Mapped[str] = mapped_column(String(200))
    sa: Mapped[int] = mapped_column(Integer)
    rule: Mapped[str] = mapped_column(String(64))
    severity: Mapped[str] = mapped_column(String(16))
    state: Mapped[str] = mapped_column(String(16), doc="active, acknowledged or cleared")
    muted: Mapped[bool] = mapped_column(Boolean, doc="raised while a mute covered it")
    message: Mapped[str] = mapped_column(String(2000))
    values: Mapped[JSONDict] = mapped_column(JsonType)
    raised_at: Mapped[float] = mapped_column(Double)
    acknowledged_at: Mapped[float | None] = mapped_column(Double)
    acknowledged_by: Mapped[str | None] = mapped_column(String(200))
    ack_comment: Mapped[str | None] = mapped_column(String(2000))
    cleared_at: Mapped[float | None] = mapped_column(Double)
    cleared_by: Mapped[str | None] = mapped_column(
        String(32), doc="condition, rule_disabled or rule_deleted"
    )
    updated_at: Mapped[float] = mapped_column(Double)


class AlertMute(Base):
    """A mute: alerts of a vehicle (or all) and a rule (or all) are recorded but not delivered."""

    __tablename__ = "alert_mutes"
    __table_args__ = (Index(None, "ends_at"),)

    id: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=True)
    vehicle_id: Mapped[str | None] = mapped_column(String(64), doc="null: every vehicle")
    rule: Mapped[str | None] = mapped_column(String(64), doc="null: every rule")
    starts_at: Mapped[float] = mapped_column(Double)
    ends_at: Mapped[float] = mapped_column(Double, doc="the expiry")
    # Quiet hours: when set, muted only inside this daily window (minutes after UTC midnight).
    daily_from_min: Mapped[int | None] = mapped_column(Integer)
    daily_to_min: Mapped[int | None] = mapped_column(Integer)
    reason: Mapped[str | None] = mapped_column(String(2000))
    created_by: Mapped[str | None] = mapped_column(String(200))
    created_at: Mapped[float] = mapped_column(Double)
    cancelled_at: Mapped[float | None] = mapped_column(Double)


class AlertEvent(Base):
    """A change of an alert, written in the same transaction: the delivery outbox's source."""

    __tablename__ = "alert_events"
    __table_args__ = (Index(None, "alert_id"),)

    id: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=True)
    alert_id: Mapped[int] = mapped_column(ForeignKey("alerts.id"))
    kind: Mapped[str] = mapped_column(String(16), doc="raised, acknowledged or cleared")
    ts: Mapped[float] = mapped_column(Double)
    payload: Mapped[JSONDict] = mapped_column(JsonType)
    muted: Mapped[bool] = mapped_column(Boolean)
