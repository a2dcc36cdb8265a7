"""Read queries of the history; each takes a sync Connection (use `AsyncConnection.run_sync`
or a thread from async code)."""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING, TypedDict

from sqlalchemy import Connection, Row, func, select
from sqlalchemy.sql.elements import ColumnElement, NamedColumn

from eqgw.store import packed
from eqgw.store.errors import StoreError
from eqgw.store.models import (
    BATTERY_METRICS,
    MEASUREMENT_METRICS,
    ROLLUP_METRICS,
    BatteryState,
    CoreTable,
    Dm1Snapshot,
    FaultEpisode,
    LiveState,
    Measurement,
    RollupDeletion,
    StatusChange,
    Unit,
    UnitOwner,
    Vehicle,
    rollup_columns,
    table_of,
)
from eqgw.store.writes import BUCKETS_S

if TYPE_CHECKING:
    from eqgw.jsontypes import JSONObject
    from eqgw.store.history_cache import HistoryCache

# (buckets, samples, first bucket start, last bucket start) of a range of one series
Fingerprint = tuple[int, int, float | None, float | None]
# A row of the rollups as `_rollup_rows` reads it: a column never NULL (bucket_ts, a count()),
# then numbers or NULLs (counts are integers, sums and extremes floats).
RollupRow = tuple[float, *tuple[float | None, ...]]

# Resolution names of `series()`: raw rows, or a rollup width in seconds.
RESOLUTIONS: dict[str, int | None] = {"raw": None, "1m": 60, "15m": 900, "1h": 3600, "1d": 86400}

_units = table_of(Unit)
_vehicles = table_of(Vehicle)
_measurements = table_of(Measurement)
_battery = table_of(BatteryState)
_rollup_deletions = table_of(RollupDeletion)
_status = table_of(StatusChange)
_dm1 = table_of(Dm1Snapshot)
_episodes = table_of(FaultEpisode)
_live = table_of(LiveState)
_owners = table_of(UnitOwner)


class UnknownMetricError(StoreError):
    """A series was asked for a metric or resolution that does not exist."""


# The rows the queries return: what the database stores, keys in column order.


class VehicleSummary(TypedDict):
    """A vehicle of `list_vehicles`, with its number of units."""

    id: str
    name: str
    depot: str | None
    units: int


class UnitRow(TypedDict):
    """A row of `units` (eqgw.store.models.Unit)."""

    id: int
    vehicle_id: str
    bus: str
    sa: int
    series: int | None
    model: str | None
    software_id: str | None
    first_seen: float | None
    last_seen: float | None
    name: str | None


# A period a NAME held a unit's address (`to` None: holds it still); `from` is a keyword.
OwnerPeriod = TypedDict("OwnerPeriod", {"name": str, "from": float, "to": float | None})


class LiveSlot(TypedDict):
    """A persisted live-state slot of a unit (`latest_values`)."""

    ts: float
    fields: JSONObject


class RawPoint(TypedDict):
    """A raw point of a series."""

    ts: float
    value: packed.Cell  # a number: metrics are numeric columns


class Bucket(TypedDict):
    """A rollup bucket of a series."""

    ts: float
    count: int
    min: float | None
    max: float | None
    avg: float | None


# A series' points: raw, or buckets (`series()`).
Point = RawPoint | Bucket


class StatusRow(TypedDict):
    """A status-flag change (`status_history`)."""

    ts: float
    flags: dict[str, str]
    changed: list[str]


class Dm1Row(TypedDict):
    """A stored DM1 snapshot (`dm1_history`)."""

    ts: float
    lamps: dict[str, int]
    dtcs: list[JSONObject]


class EpisodeRow(TypedDict):
    """A row of `fault_episodes` (eqgw.store.models.FaultEpisode)."""

    id: int
    unit_id: int
    fault: str
    spn: int | None
    fmi: int | None
    source: str
    state: str
    started_at: float
    last_seen_at: float
    ended_at: float | None
    ended_by: str | None
    occurrence_count: int | None


class UnitEpisodeRow(EpisodeRow):
    """A fault episode with its unit's vehicle, bus and address (`fault_episodes()`)."""

    vehicle_id: str
    bus: str
    sa: int


class FaultCount(TypedDict):
    """A fault's figures of a unit (`fault_counts`)."""

    episodes: int
    occurrence_count: int | None
    last_started_at: float | None


class RestartUnitRow(UnitRow):
    """A unit as `restart_state` gives it back: its row, its live slots (name -> (ts,
    fields)) and its open episodes."""

    live: dict[str, tuple[float, JSONObject]]
    episodes: list[EpisodeRow]


def _unit_row(r: Row[*tuple[object, ...]]) -> UnitRow:
    return {
        "id": r.id,
        "vehicle_id": r.vehicle_id,
        "bus": r.bus,
        "sa": r.sa,
        "series": r.series,
        "model": r.model,
        "software_id": r.software_id,
        "first_seen": r.first_seen,
        "last_seen": r.last_seen,
        "name": r.name,
    }


def metrics() -> list[str]:
    """Every metric `series()` serves."""
    battery = [f"{m}_{b}" for m in BATTERY_METRICS if m != "temperature_c" for b in ("12v", "24v")]
    return [*MEASUREMENT_METRICS, *battery, "temperature_c"]


def list_vehicles(conn: Connection) -> list[VehicleSummary]:
    """Vehicles with their number of units (retired ones left out)."""
    n = func.count(_units.c.id)
    stmt = (
        select(_vehicles.c.id, _vehicles.c.name, _vehicles.c.depot, n.label("units"))
        .select_from(_vehicles.outerjoin(_units, _units.c.vehicle_id == _vehicles.c.id))
        .where(_vehicles.c.retired_at.is_(None))
        .group_by(_vehicles.c.id, _vehicles.c.name, _vehicles.c.depot)
        .order_by(_vehicles.c.id)
    )
    return [
        {"id": v, "name": name, "depot": depot, "units": n}
        for v, name, depot, n in conn.execute(stmt)
    ]


def list_units(conn: Connection, vehicle_id: str | None = None) -> list[UnitRow]:
    """Units (of one vehicle, if given): bus, SA, series, model, software id, first/last seen."""
    stmt = select(_units).order_by(_units.c.vehicle_id, _units.c.bus, _units.c.sa)
    if vehicle_id is not None:
        stmt = stmt.where(_units.c.vehicle_id == vehicle_id)
    return [_unit_row(r) for r in conn.execute(stmt)]


def get_unit(conn: Connection, unit_id: int) -> UnitRow | None:
    """One unit by id."""
    row = conn.execute(select(_units).where(_units.c.id == unit_id)).first()
    return _unit_row(row) if row else None


def unit_id_of(conn: Connection, bus: str, sa: int) -> int | None:
    """The id of the unit at (bus, source address)."""
    return conn.execute(
        select(_units.c.id).where(_units.c.bus == bus, _units.c.sa == sa)
    ).scalar_one_or_none()


def unit_owners(
    conn: Connection, unit_id: int, start: float | None = None, end: float | None = None
) -> list[OwnerPeriod]:
    """The NAMEs that held a unit's address, oldest first, as periods {name, from, to} (`to`
    None: holds it still); with `start`/`end`, only the periods overlapping [start, end)."""
    o = _owners.c
    rows = conn.execute(select(o.since, o.name).where(o.unit_id == unit_id).order_by(o.since)).all()
    periods: list[OwnerPeriod] = []
    for since, name in rows:
        if periods and periods[-1]["name"] == name:
            continue  # the same node claiming again (a restart, another log)
        if periods:
            periods[-1]["to"] = since
        periods.append({"name": name, "from": since, "to": None})
    return [
        p
        for p in periods
        if (end is None or p["from"] < end)
        and (start is None or p["to"] is None or p["to"] > start)
    ]


def latest_values(conn: Connection, unit_id: int) -> dict[str, LiveSlot]:
    """Persisted live state of a unit: slot (`voltages`, `battery_states/2`, ...) -> ts, fields."""
    stmt = select(_live.c.name, _live.c.ts, _live.c.fields).where(_live.c.unit_id == unit_id)
    return {name: {"ts": ts, "fields": fields} for name, ts, fields in conn.execute(stmt)}


def _metric_source(
    metric: str,
) -> tuple[CoreTable, NamedColumn[float], list[ColumnElement[bool]]]:
    """(table, value column, extra WHERE clauses) of a metric's raw rows."""
    if metric in MEASUREMENT_METRICS:
        return _measurements, _measurements.c[metric], []
    if metric == "temperature_c":
        return _battery, _battery.c.temperature_c, [_battery.c.idx == 5]
    base, _, battery = metric.rpartition("_")
    if base in BATTERY_METRICS and battery in ("12v", "24v"):
        return _battery, _battery.c[base], [_battery.c.battery == battery]
    raise UnknownMetricError(f"unknown metric {metric!r}; known: {', '.join(metrics())}")


def series(
    conn: Connection,
    unit_id: int,
    metric: str,
    start: float,
    end: float,
    resolution: str = "raw",
    *,
    limit: int | None = None,
) -> list[RawPoint] | list[Bucket]:
    """A metric over [start, end): raw points `{ts, value}`, or buckets
    `{ts, count, min, max, avg}` read from the rollups (never from the raw rows)."""
    if resolution not in RESOLUTIONS:
        raise UnknownMetricError(
            f"unknown resolution {resolution!r}; use one of {', '.join(RESOLUTIONS)}"
        )
    table, column, where = _metric_source(metric)
    width = RESOLUTIONS[resolution]
    if width is None:
        return _raw_points(conn, unit_id, metric, table, column, where, start, end, limit)
    return series_many(conn, unit_id, [metric], start, end, resolution, limit=limit)[metric]


def _raw_points(
    conn: Connection,
    unit_id: int,
    metric: str,
    table: CoreTable,
    column: NamedColumn[float],
    where: list[ColumnElement[bool]],
    start: float,
    end: float,
    limit: int | None,
) -> list[RawPoint]:
    """A metric's raw points: the table's rows, and the rows packed into blocks
    (eqgw.store.packed) merged in key order; a row in both (read while being packed) once."""
    key = [table.c.ts, *(c for c in table.primary_key.columns if c.name not in ("unit_id", "ts"))]
    stmt = (
        select(table.c.ts, column, *key[1:])
        .where(table.c.unit_id == unit_id, table.c.ts >= start, table.c.ts < end, *where)
        .where(column.is_not(None))
        .order_by(*key)
    )
    if limit is not None:
        stmt = stmt.limit(limit)
    # One fetch of every row: iterating the result fetches row by row, twice the cost.
    # The rows first, then the blocks: a row packed in between is read twice, never missed.
    rows = conn.execute(stmt).all()
    s = packed.MEASUREMENTS if table is _measurements else packed.BATTERY_STATES
    at = s.columns.index(column.name)
    test = _packed_filter(s, metric)
    blocks = packed.read_rows(
        conn, s, unit_id, start, end, keep=lambda r: r[at] is not None and test(r), limit=limit
    )
    if not blocks:
        return [{"ts": ts, "value": v} for ts, v, *_ in rows]
    keys = [s.columns.index(c.name) for c in key[1:]]
    points: dict[packed.Values, packed.Cell] = {
        (r[0], *(r[k] for k in keys)): r[at] for r in blocks
    }
    for ts, v, *rest in rows:
        points.setdefault((ts, *rest), v)
    out: list[RawPoint] = [
        {"ts": k[0], "value": v} for k, v in sorted(points.items(), key=lambda kv: kv[0])
    ]
    return out[:limit] if limit is not None else out


def _packed_filter(s: packed.Series, metric: str) -> Callable[[packed.Values], bool]:
    """The WHERE clauses of `_metric_source` on a packed row (values in column order)."""
    if s is packed.MEASUREMENTS:
        return lambda _r: True
    if metric == "temperature_c":
        at = s.columns.index("idx")
        return lambda r: r[at] == 5
    battery = metric.rpartition("_")[2]
    at = s.columns.index("battery")
    return lambda r: r[at] == battery


def series_many(
    conn: Connection,
    unit_id: int,
    metrics: list[str],
    start: float,
    end: float,
    resolution: str = "raw",
    *,
    limit: int | None = None,
    cache: HistoryCache | None = None,
) -> dict[str, list[RawPoint] | list[Bucket]]:
    """`series()` of several metrics; rollup buckets of all of them come from one query,
    read through the driver's cursor (SQLAlchemy's row processing costs as much again as
    the read for the thousands of buckets of a day at 1 min), or from `cache`, which
    checks what it holds against the database on every use."""
    for metric in metrics:
        _metric_source(metric)  # unknown metrics raise before any query
    if resolution not in RESOLUTIONS:
        raise UnknownMetricError(
            f"unknown resolution {resolution!r}; use one of {', '.join(RESOLUTIONS)}"
        )
    width = RESOLUTIONS[resolution]
    if width is None or not metrics:
        return {m: series(conn, unit_id, m, start, end, resolution, limit=limit) for m in metrics}
    if cache is not None:
        buckets = cache.series(conn, unit_id, metrics, start, end, width)
    else:
        buckets = read_rollups(conn, unit_id, metrics, width, start, end)
    out: dict[str, list[RawPoint] | list[Bucket]] = {
        m: p[:limit] if limit is not None and len(p) > limit else p for m, p in buckets.items()
    }
    return out


def _marks(conn: Connection, n: int) -> str:
    return ", ".join(["?" if conn.dialect.paramstyle == "qmark" else "%s"] * n)


def _rollup_rows(
    conn: Connection,
    columns: str,
    unit_id: int,
    width: int,
    start: float,
    end: float,
    tail: str,
) -> list[RollupRow]:
    """`SELECT columns FROM rollups` of a unit at one width, over bucket starts in
    [start, end), through the driver's cursor."""
    mark = _marks(conn, 1)
    raw = conn.connection.driver_connection
    assert raw is not None
    cur = raw.cursor()
    try:
        cur.execute(
            f"SELECT {columns} FROM rollups WHERE unit_id = {mark} AND bucket_s = {mark} "
            f"AND bucket_ts >= {mark} AND bucket_ts < {mark} {tail}",
            (unit_id, width, start, end),
        )
        rows: list[RollupRow] = cur.fetchall()
    finally:
        cur.close()
    return rows


def _rollup_metrics(metrics: Sequence[str]) -> list[str]:
    """The metrics that have rollups, each once (a metric without any has no buckets)."""
    return [m for m in dict.fromkeys(metrics) if m in ROLLUP_METRICS]


def read_rollups(
    conn: Connection, unit_id: int, metrics: Sequence[str], width: int, start: float, end: float
) -> dict[str, list[Bucket]]:
    """The rollup buckets of `metrics` whose start is in [start, end), oldest first, as
    points `{ts, count, min, max, avg}` (a bucket belongs to a range when its start does:
    the usual convention of chart APIs). A metric has a bucket where its count is set."""
    out: dict[str, list[Bucket]] = {m: [] for m in metrics}
    wanted = _rollup_metrics(metrics)
    if not wanted or not end > start:
        return out
    columns = ", ".join(c for m in wanted for c in rollup_columns(m))
    rows = _rollup_rows(
        conn, f"bucket_ts, {columns}", unit_id, width, start, end, "ORDER BY bucket_ts"
    )
    lists = [out[m] for m in wanted]
    for row in rows:
        ts = row[0]
        at = 1
        for points in lists:
            n = row[at]
            if n is not None:
                total = row[at + 1]
                points.append(
                    {
                        "ts": ts,
                        "count": int(n),
                        "min": row[at + 2],
                        "max": row[at + 3],
                        "avg": total / n if n and total is not None else None,
                    }
                )
            at += 4
    return out


def rollup_generation(conn: Connection, unit_id: int) -> int:
    """How many times the unit's rollups have been deleted (0: never); see
    eqgw.store.retention.bump_rollup_generation."""
    row = conn.execute(
        select(_rollup_deletions.c.generation).where(_rollup_deletions.c.unit_id == unit_id)
    ).first()
    return int(row[0]) if row else 0


def rollup_fingerprints(
    conn: Connection, unit_id: int, metrics: Sequence[str], width: int, start: float, end: float
) -> dict[str, Fingerprint]:
    """Per metric, over bucket starts in [start, end): (buckets, samples, first bucket start,
    last bucket start), aggregated by the database without a row per bucket reaching Python.

    Rollups only change by merges, which add at least one sample to a bucket, by new buckets,
    and by the retention deleting the oldest buckets: any of them alone changes a range's
    fingerprint. A deletion and a bucket made again with as many samples do not; for that,
    `rollup_generation` (eqgw.store.history_cache checks both)."""
    out: dict[str, Fingerprint] = dict.fromkeys(metrics, (0, 0, None, None))
    wanted = _rollup_metrics(metrics)
    if not wanted or not end > start:
        return out
    aggregates = []
    for m in wanted:
        c = rollup_columns(m)[0]
        at = f"CASE WHEN {c} IS NOT NULL THEN bucket_ts END"
        aggregates += [f"count({c})", f"sum({c})", f"min({at})", f"max({at})"]
    rows = _rollup_rows(conn, ", ".join(aggregates), unit_id, width, start, end, "")
    if not rows:
        return out
    row = rows[0]
    for i, m in enumerate(wanted):
        n, samples, first, last = row[4 * i : 4 * i + 4]
        if n:
            out[m] = (int(n), int(samples or 0), first, last)
    return out


def bucket_count(start: float, end: float, width: int) -> int:
    """How many buckets of `width` s start in [start, end): the most points a rollup series
    of the range can have, known without reading a row."""
    if end <= start:
        return 0
    return max(math.ceil(end / width) - math.ceil(start / width), 0)


def pick_resolution(start: float, end: float, max_points: int = 1000) -> str:
    """The finest resolution that returns at most about `max_points` buckets (raw is 3 s)."""
    span = max(end - start, 0.0)
    if span / 3.0 <= max_points:
        return "raw"
    for name, width in RESOLUTIONS.items():
        if width is not None and span / width <= max_points:
            return name
    return "1d"


def status_history(
    conn: Connection, unit_id: int, start: float, end: float, *, limit: int | None = None
) -> list[StatusRow]:
    """Status-flag changes of a unit in [start, end), oldest first."""
    s = _status.c
    stmt = (
        select(s.ts, s.flags, s.changed)
        .where(s.unit_id == unit_id, s.ts >= start, s.ts < end)
        .order_by(s.ts)
    )
    if limit is not None:
        stmt = stmt.limit(limit)
    return [
        {"ts": ts, "flags": flags, "changed": changed} for ts, flags, changed in conn.execute(stmt)
    ]


def dm1_history(
    conn: Connection, unit_id: int, start: float, end: float, *, limit: int | None = None
) -> list[Dm1Row]:
    """DM1 snapshots (stored when their content changed) of a unit in [start, end)."""
    d = _dm1.c
    stmt = (
        select(d.ts, d.lamps, d.dtcs)
        .where(d.unit_id == unit_id, d.ts >= start, d.ts < end)
        .order_by(d.ts)
    )
    if limit is not None:
        stmt = stmt.limit(limit)
    return [{"ts": ts, "lamps": lamps, "dtcs": dtcs} for ts, lamps, dtcs in conn.execute(stmt)]


def fault_episodes(
    conn: Connection,
    unit_id: int | None = None,
    *,
    start: float | None = None,
    end: float | None = None,
    fault: str | None = None,
    open_only: bool = False,
    vehicle_id: str | None = None,
    vehicle_ids: Sequence[str] | None = None,
    after_id: int | None = None,
    limit: int | None = None,
) -> list[UnitEpisodeRow]:
    """Fault episodes overlapping [start, end), newest first; `open_only` for active/stale;
    with `vehicle_ids` (a key's scope) only theirs. With `after_id`, a page of an export
    instead: those of id above it, in id order (at most `limit`)."""
    e = _episodes.c
    stmt = select(_episodes, _units.c.vehicle_id, _units.c.bus, _units.c.sa).join(
        _units, _units.c.id == e.unit_id
    )
    if unit_id is not None:
        stmt = stmt.where(e.unit_id == unit_id)
    if vehicle_id is not None:
        stmt = stmt.where(_units.c.vehicle_id == vehicle_id)
    if vehicle_ids is not None:
        stmt = stmt.where(_units.c.vehicle_id.in_(list(vehicle_ids)))
    if fault is not None:
        stmt = stmt.where(e.fault == fault)
    if open_only:
        stmt = stmt.where(e.state != "closed")
    if end is not None:
        stmt = stmt.where(e.started_at < end)
    if start is not None:
        stmt = stmt.where(e.ended_at.is_(None) | (e.ended_at >= start))
    if after_id is not None:
        stmt = stmt.where(e.id > after_id).order_by(e.id)
    else:
        stmt = stmt.order_by(e.started_at.desc(), e.id.desc())
    if limit is not None:
        stmt = stmt.limit(limit)
    return [
        {**_episode_row(r), "vehicle_id": r.vehicle_id, "bus": r.bus, "sa": r.sa}
        for r in conn.execute(stmt)
    ]


def _episode_row(r: Row[*tuple[object, ...]]) -> EpisodeRow:
    return {
        "id": r.id,
        "unit_id": r.unit_id,
        "fault": r.fault,
        "spn": r.spn,
        "fmi": r.fmi,
        "source": r.source,
        "state": r.state,
        "started_at": r.started_at,
        "last_seen_at": r.last_seen_at,
        "ended_at": r.ended_at,
        "ended_by": r.ended_by,
        "occurrence_count": r.occurrence_count,
    }


def fault_counts(conn: Connection, unit_id: int) -> dict[str, FaultCount]:
    """Per fault: eqgw's count of episodes, and the occurrence count the unit reported last
    (DM1 OC; a unit may reset it, so it is not a maximum)."""
    e = _episodes.c
    stmt = (
        select(e.fault, e.started_at, e.occurrence_count)
        .where(e.unit_id == unit_id)
        .order_by(e.fault, e.started_at)
    )
    out: dict[str, FaultCount] = {}
    for fault, started, oc in conn.execute(stmt):
        cur = out.setdefault(
            fault, {"episodes": 0, "occurrence_count": None, "last_started_at": None}
        )
        cur["episodes"] += 1
        cur["last_started_at"] = started
        if oc is not None:
            cur["occurrence_count"] = oc
    return out


def row_counts(conn: Connection) -> dict[str, int]:
    """Rows per history table (for summaries and tests); `raw_frames`: the frames of the raw
    archive (packed in raw_blocks or waiting in raw_recent); `measurements` and
    `battery_states` count their rows packed into blocks too."""
    from eqgw.store.archive import count_frames
    from eqgw.store.models import metadata

    counts = {
        name: conn.execute(select(func.count()).select_from(t)).scalar_one()
        for name, t in sorted(metadata.tables.items())
    }
    counts["raw_frames"] = count_frames(conn)
    # Rows packed into blocks (eqgw.store.packed) are rows of their table still.
    for name, n in packed.packed_counts(conn).items():
        counts[name] += n
    return counts


__all__ = [
    "BUCKETS_S",
    "RESOLUTIONS",
    "UnknownMetricError",
    "dm1_history",
    "fault_counts",
    "fault_episodes",
    "get_unit",
    "latest_values",
    "list_units",
    "list_vehicles",
    "metrics",
    "pick_resolution",
    "row_counts",
    "series",
    "status_history",
    "unit_id_of",
    "unit_owners",
]


def restart_state(conn: Connection, buses: Sequence[str]) -> list[RestartUnitRow]:
    """What a restarting gateway takes back for the units of `buses`: the unit row
    (bus, sa, series, model, software_id, first_seen, last_seen), its persisted live state
    (`live`: name -> (ts, fields)) and its open episodes (`episodes`: active or stale rows)."""
    if not buses:
        return []
    u = _units.c
    units: dict[int, RestartUnitRow] = {}
    for row in conn.execute(select(_units).where(u.bus.in_(list(buses))).order_by(u.id)):
        units[row.id] = {**_unit_row(row), "live": {}, "episodes": []}
    if not units:
        return []
    ids = list(units)
    for uid, name, ts, fields in conn.execute(
        select(_live.c.unit_id, _live.c.name, _live.c.ts, _live.c.fields).where(
            _live.c.unit_id.in_(ids)
        )
    ):
        units[uid]["live"][name] = (ts, fields)
    e = _episodes.c
    for row in conn.execute(
        select(_episodes)
        .where(e.unit_id.in_(ids), e.state.in_(("active", "stale")))
        .order_by(e.started_at, e.id)
    ):
        units[row.unit_id]["episodes"].append(_episode_row(row))
    return list(units.values())
