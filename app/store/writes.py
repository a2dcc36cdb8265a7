"""The ingest's write path: one batch of rows in one transaction, idempotent on both engines."""

from __future__ import annotations

import math
import struct
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from operator import itemgetter
from typing import TYPE_CHECKING, TypedDict, TypeVar, cast

from sqlalchemy import (
    JSON,
    BindParameter,
    Connection,
    bindparam,
    case,
    exists,
    select,
    update,
)
from sqlalchemy.dialects import postgresql, sqlite
from sqlalchemy.sql.selectable import Exists

from eqgw.jsontypes import JSONObject, JSONValue
from eqgw.store import archive, packed
from eqgw.store.blockrows import pg_array
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
    Message,
    RawRecent,
    Rollup,
    StatusChange,
    Unit,
    UnitOwner,
    Vehicle,
    rollup_columns,
    table_of,
)

if TYPE_CHECKING:
    import psycopg
    from psycopg.rows import TupleRow

# Rollup bucket widths in seconds. Each divides the next, so wider buckets are merged from
# the 1-minute deltas instead of re-walking the rows.
BUCKETS_S = (60, 900, 3600, 86400)

UnitKey = tuple[str, int]  # (bus, source address)
EpisodeKey = tuple[UnitKey, str, float]  # (unit, fault, started_at)
LiveKey = tuple[UnitKey, str]  # (unit, live slot)

_measurements = table_of(Measurement)
_battery = table_of(BatteryState)
_status = table_of(StatusChange)
_dm1 = table_of(Dm1Snapshot)
_messages = table_of(Message)
_raw_recent = table_of(RawRecent)
_episodes = table_of(FaultEpisode)
_live = table_of(LiveState)
_units = table_of(Unit)
_owners = table_of(UnitOwner)
_vehicles = table_of(Vehicle)
# The tables a row is appended to; their rows go to the database as `TableRow`s.
_APPEND_ONLY = (_measurements, _battery, _status, _dm1, _messages, _raw_recent)
for _table in _APPEND_ONLY:
    if [c.name for c in _table.columns][:2] != ["unit_id", "ts"]:  # pragma: no cover
        raise TypeError(f"{_table.name}: its columns do not begin (unit_id, ts)")


# The values of one row of each table, without its unit_id (the writer adds it). Values
# copied from a decoded record's fields are typed as JSON, as the record has them.
class MeasurementValues(TypedDict):
    ts: float
    v12: JSONValue
    v24: JSONValue
    i12: JSONValue
    i24: JSONValue


class BatteryValues(TypedDict):
    ts: float
    idx: JSONValue
    battery: JSONValue
    soc: JSONValue
    soc_achievable: JSONValue
    soh: JSONValue
    dod: JSONValue
    runtime_min: JSONValue
    runtime_temp_adj_min: JSONValue
    major_12v: JSONValue
    minor_12v: JSONValue
    major_24v: JSONValue
    minor_24v: JSONValue
    temperature_c: JSONValue
    temperature_raw: JSONValue


class StatusValues(TypedDict):
    ts: float
    flags: JSONObject
    changed: list[str]


class Dm1Values(TypedDict):
    ts: float
    lamps: JSONValue
    dtcs: JSONValue


class MessageValues(TypedDict):
    ts: float
    name: str
    idx: JSONValue
    fields: JSONObject


class RawFrameValues(TypedDict):
    ts: float
    can_id: int
    seq: int
    data: bytes


class EpisodeValues(TypedDict):
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


class LiveValues(TypedDict):
    ts: float
    fields: JSONObject


class VehicleInfo(TypedDict):
    id: str
    name: str
    depot: str | None


class UnitInfo(TypedDict, total=False):
    """Identification learned from a unit (the keys present are the ones learned)."""

    ts: float
    series: JSONValue
    model: JSONValue
    software_id: JSONValue


TableValues = (
    MeasurementValues | BatteryValues | StatusValues | Dm1Values | MessageValues | RawFrameValues
)
# One row of an append-only table: its unit and its values.
KeyedValues = tuple[UnitKey, Mapping[str, object]]
# The same row as it goes to the database: its values in table column order, the unit's id
# first, the time second (every append-only table starts (unit_id, ts): _APPEND_ONLY).
TableRow = tuple[int, float, *tuple[object, ...]]


@dataclass(slots=True)
class Batch:
    """Rows gathered by the writer for one transaction, grouped by destination."""

    vehicles: dict[str, VehicleInfo] = field(default_factory=dict)
    units: dict[UnitKey, str] = field(default_factory=dict)  # unit -> vehicle id
    unit_info: dict[UnitKey, UnitInfo] = field(default_factory=dict)
    # unit -> [(since, NAME)]: the NAMEs that took its address, in the order seen
    unit_owners: dict[UnitKey, list[tuple[float, str]]] = field(default_factory=dict)
    measurements: list[tuple[UnitKey, MeasurementValues]] = field(default_factory=list)
    battery_states: list[tuple[UnitKey, BatteryValues]] = field(default_factory=list)
    status_changes: list[tuple[UnitKey, StatusValues]] = field(default_factory=list)
    dm1_snapshots: list[tuple[UnitKey, Dm1Values]] = field(default_factory=list)
    messages: list[tuple[UnitKey, MessageValues]] = field(default_factory=list)
    # into eqgw.store.archive
    raw_frames: list[tuple[UnitKey, RawFrameValues]] = field(default_factory=list)
    episodes: dict[EpisodeKey, EpisodeValues] = field(default_factory=dict)
    live: dict[LiveKey, LiveValues] = field(default_factory=dict)
    seen: dict[UnitKey, list[float]] = field(default_factory=dict)  # unit -> [first, last]
    rows: int = 0

    def touched_units(self) -> set[UnitKey]:
        keys: set[UnitKey] = set(self.units)
        keys.update(self.seen)
        keys.update(self.unit_info)
        keys.update(self.unit_owners)
        for rows in (
            self.measurements,
            self.battery_states,
            self.status_changes,
            self.dm1_snapshots,
            self.messages,
            self.raw_frames,
        ):
            keys.update(r[0] for r in rows)
        keys.update(k[0] for k in self.episodes)
        keys.update(k[0] for k in self.live)
        return keys


@dataclass(slots=True)
class BatchResult:
    """What one committed batch changed."""

    unit_ids: dict[UnitKey, int]
    inserted: dict[str, int]
    rollup_buckets: int


def dialect_insert(conn: Connection, table: CoreTable) -> postgresql.Insert | sqlite.Insert:
    """`INSERT` with the dialect's ON CONFLICT support (PostgreSQL or SQLite)."""
    if conn.dialect.name == "postgresql":
        return postgresql.insert(table)
    return sqlite.insert(table)


def _pk(table: CoreTable) -> list[str]:
    return [c.name for c in table.primary_key.columns]


def ensure_units(
    conn: Connection,
    units: dict[UnitKey, str],
    known: dict[UnitKey, int],
) -> dict[UnitKey, int]:
    """Ids of the given units, inserting the ones the database does not have yet."""
    missing = [k for k in units if k not in known]
    if not missing:
        return {}
    stmt = dialect_insert(conn, _units).on_conflict_do_nothing(index_elements=["bus", "sa"])
    conn.execute(stmt, [{"bus": b, "sa": s, "vehicle_id": units[(b, s)]} for b, s in missing])
    found: dict[UnitKey, int] = {}
    buses = sorted({b for b, _ in missing})
    for uid, bus, sa in conn.execute(
        select(_units.c.id, _units.c.bus, _units.c.sa).where(_units.c.bus.in_(buses))
    ):
        if (bus, sa) in units:
            found[(bus, sa)] = uid
    return found


def ensure_vehicles(conn: Connection, vehicles: Iterable[VehicleInfo], update_: bool) -> None:
    """Insert vehicles; with `update_`, configuration wins over what the database holds."""
    rows = list(vehicles)
    if not rows:
        return
    ins = dialect_insert(conn, _vehicles)
    if update_:
        stmt = ins.on_conflict_do_update(
            index_elements=["id"], set_={"name": ins.excluded.name, "depot": ins.excluded.depot}
        )
    else:
        stmt = ins.on_conflict_do_nothing(index_elements=["id"])
    conn.execute(stmt, rows)


def _params(rows: Sequence[KeyedValues], ids: dict[UnitKey, int]) -> list[dict[str, object]]:
    return [{"unit_id": ids[key], **values} for key, values in rows]


def _insert_new(
    conn: Connection, table: CoreTable, rows: Sequence[KeyedValues], ids: dict[UnitKey, int]
) -> int:
    """SQLite: insert, skipping rows whose natural key exists (replays, retried batches)."""
    if not rows:
        return 0
    if not _has_json(table):
        return len(_sqlite_insert_new(conn, table, rows, ids))
    stmt = dialect_insert(conn, table).on_conflict_do_nothing(index_elements=_pk(table))
    result = conn.execute(stmt, _params(rows, ids))
    return max(result.rowcount, 0)


def _insert_returning(
    conn: Connection,
    table: CoreTable,
    rows: Sequence[KeyedValues],
    ids: dict[UnitKey, int],
    columns: Sequence[str],
) -> list[Sequence[object]]:
    """SQLite: insert, returning only the rows really inserted (the rollups count each
    row once)."""
    if not rows:
        return []
    if not _has_json(table):
        new = _sqlite_insert_new(conn, table, rows, ids)
        positions = [c.name for c in table.columns]
        pick = itemgetter(*(positions.index(c) for c in columns))
        return [pick(row) for row in new]
    stmt = (
        dialect_insert(conn, table)
        .on_conflict_do_nothing(index_elements=_pk(table))
        .returning(*(table.c[c] for c in columns))
    )
    return list(conn.execute(stmt, _params(rows, ids)).all())


def _has_json(table: CoreTable) -> bool:
    return any(isinstance(c.type, JSON) for c in table.columns)


def _sqlite_insert_new(
    conn: Connection, table: CoreTable, rows: Sequence[KeyedValues], ids: dict[UnitKey, int]
) -> list[TableRow]:
    """SQLite, tables without JSON columns: the rows whose key is new, inserted with one
    DB-API executemany of plain tuples (SQLAlchemy's per-row parameter processing costs
    more than SQLite's insert). The caller's transaction holds SQLite's write lock
    (BEGIN IMMEDIATE), so the existing keys read first cannot change before the insert.
    Returns the inserted rows as tuples in table column order (unit_id first); within the
    batch the first row of a key wins, as with ON CONFLICT DO NOTHING."""
    cols = [c.name for c in table.columns]
    pk = _pk(table)
    values_of = itemgetter(*cols[1:])  # unit_id first, from `ids`
    params = [(ids[key], *values_of(values)) for key, values in rows]
    raw = conn.connection.driver_connection
    assert raw is not None
    # Keys already stored in the batch's time range of each unit (none on a first load).
    spans: dict[int, list[float]] = {}
    _spans(params, spans)
    seen: set[object] = set()
    pk_list = ", ".join(pk)
    for uid, (lo, hi) in spans.items():
        cur = raw.execute(
            f"SELECT {pk_list} FROM {table.name} WHERE unit_id = ? AND ts BETWEEN ? AND ?",
            (uid, lo, hi),
        )
        seen.update(cur.fetchall() if len(pk) > 1 else (r[0] for r in cur.fetchall()))
    new = _first_of_each_key(table, cols, params, seen)
    if new:
        marks = ", ".join("?" * len(cols))
        raw.executemany(
            f"INSERT INTO {table.name} ({', '.join(cols)}) VALUES ({marks}) ON CONFLICT DO NOTHING",
            new,
        )
    return new


def _pg_insert_lists(
    conn: Connection,
    lists: Sequence[tuple[CoreTable, Sequence[KeyedValues]]],
    ids: dict[UnitKey, int],
) -> dict[str, list[TableRow]]:
    """PostgreSQL: the rows of the append-only tables whose keys are new, COPYed straight
    into their tables. Returns each table's inserted rows (tuples in column order).

    Repeats within the batch are dropped (the first row of a key wins, as with ON CONFLICT
    DO NOTHING), and so are keys already stored: one query first asks whether any table
    holds a row in a unit's time range of the batch, and only then are the stored keys
    read table by table. Live data is newer than anything stored, so the usual batch costs
    that one query, and its rows go in by plain COPY, cheaper on the server
    than INSERT ... ON CONFLICT. Should another writer store one of the keys between the
    check and the COPY, the COPY (inside a savepoint) fails with a unique violation and
    the rows take the conflict-safe path instead (`_pg_upsert_copy`)."""
    from psycopg import errors as pg_errors

    todo = [(t, [c.name for c in t.columns], rows) for t, rows in lists if rows]
    if not todo:
        return {}
    params = {t.name: _pg_params(t, cols, rows, ids) for t, cols, rows in todo}
    raw = conn.connection.driver_connection
    assert raw is not None
    spans: dict[int, list[float]] = {}
    for t, _, _ in todo:
        _spans(params[t.name], spans)
    stored = _pg_any_stored(raw, [t.name for t, _, _ in todo], spans)
    new = {
        t.name: (
            _new_keys_only(raw, t, cols, params[t.name])
            if stored
            else _first_of_each_key(t, cols, params[t.name], set())
        )
        for t, cols, _ in todo
    }
    with raw.cursor() as cur:
        cur.execute("SAVEPOINT eqgw_copy")
        try:
            for t, cols, _ in todo:
                if new[t.name]:
                    _copy_rows(cur, t.name, t, cols, new[t.name])
        except pg_errors.UniqueViolation:
            cur.execute("ROLLBACK TO SAVEPOINT eqgw_copy")
            return {
                t.name: _pg_upsert_copy(cur, t, cols, new[t.name]) if new[t.name] else []
                for t, cols, _ in todo
            }
        cur.execute("RELEASE SAVEPOINT eqgw_copy")
    return new


def _pg_params(
    table: CoreTable, cols: list[str], rows: Sequence[KeyedValues], ids: dict[UnitKey, int]
) -> list[TableRow]:
    """Rows as tuples in column order, unit_id first (JSON values wrapped for psycopg)."""
    from psycopg.types.json import Jsonb

    json_cols = {c.name for c in table.columns if isinstance(c.type, JSON)}
    value_cols = cols[1:]  # unit_id first, from `ids`
    if json_cols:
        # The values read by name are `object`s: the row's time (ts, the first) is the float
        # its TypedDict holds.
        return cast(
            "list[TableRow]",
            [
                (ids[key], *(Jsonb(values[c]) if c in json_cols else values[c] for c in value_cols))
                for key, values in rows
            ],
        )
    values_of = itemgetter(*value_cols)
    return [(ids[key], *values_of(values)) for key, values in rows]


def _spans(params: list[TableRow], spans: dict[int, list[float]]) -> None:
    """Widen `spans` (unit id -> [first ts, last ts]) to cover `params`."""
    for p in params:
        ts = p[1]
        span = spans.get(p[0])
        if span is None:
            spans[p[0]] = [ts, ts]
        elif ts < span[0]:
            span[0] = ts
        elif ts > span[1]:
            span[1] = ts


def _span_arrays(spans: dict[int, list[float]]) -> tuple[str, str, str]:
    uids = list(spans)
    return (
        pg_array(uids),
        pg_array([spans[u][0] for u in uids]),
        pg_array([spans[u][1] for u in uids]),
    )


def _pg_any_stored(
    raw: psycopg.Connection[TupleRow], tables: list[str], spans: dict[int, list[float]]
) -> bool:
    """Whether any of `tables` holds a row of a unit within that unit's span."""
    probes = " OR ".join(
        f"EXISTS (SELECT 1 FROM s JOIN {t} t ON t.unit_id = s.u AND t.ts BETWEEN s.lo AND s.hi)"
        for t in tables
    )
    with raw.cursor() as cur:
        cur.execute(
            "WITH s(u, lo, hi) AS (SELECT * FROM unnest(%s::int[], %s::float8[], %s::float8[])) "
            f"SELECT {probes}",
            _span_arrays(spans),
        )
        row = cur.fetchone()
    return bool(row and row[0])


def _first_of_each_key(
    table: CoreTable, cols: list[str], params: list[TableRow], seen: set[object]
) -> list[TableRow]:
    """The rows whose primary key is not in `seen`, nor repeated earlier in `params`."""
    key_of = itemgetter(*(cols.index(c) for c in _pk(table)))
    if not seen:
        keys = list(map(key_of, params))
        if len(set(keys)) == len(keys):
            return params  # the usual case: no repeats
    new: list[TableRow] = []
    for p in params:
        k = key_of(p)
        if k not in seen:
            seen.add(k)
            new.append(p)
    return new


def _new_keys_only(
    raw: psycopg.Connection[TupleRow], table: CoreTable, cols: list[str], params: list[TableRow]
) -> list[TableRow]:
    """The rows whose primary key is neither stored nor repeated earlier in `params`."""
    pk = _pk(table)
    spans: dict[int, list[float]] = {}
    _spans(params, spans)
    pk_list = ", ".join(f"t.{c}" for c in pk)
    with raw.cursor() as cur:
        cur.execute(
            f"SELECT {pk_list} FROM unnest(%s::int[], %s::float8[], %s::float8[]) AS s(u, lo, hi) "
            f"JOIN {table.name} t ON t.unit_id = s.u AND t.ts BETWEEN s.lo AND s.hi",
            _span_arrays(spans),
        )
        stored = cur.fetchall()
    seen: set[object] = set(stored) if len(pk) > 1 else {r[0] for r in stored}
    return _first_of_each_key(table, cols, params, seen)


def _pg_upsert_copy(
    cur: psycopg.Cursor[TupleRow], table: CoreTable, cols: list[str], params: list[TableRow]
) -> list[TableRow]:
    """The conflict-safe path: COPY into a temporary table, then INSERT ... SELECT ... ON
    CONFLICT DO NOTHING, returning the rows really inserted (in column order)."""
    tmp = f"eqgw_tmp_{table.name}"
    col_list = ", ".join(cols)
    cur.execute(f"CREATE TEMP TABLE IF NOT EXISTS {tmp} (LIKE {table.name}) ON COMMIT DELETE ROWS")
    _copy_rows(cur, tmp, table, cols, params)
    cur.execute(
        f"INSERT INTO {table.name} ({col_list}) SELECT {col_list} FROM {tmp} "
        f"ON CONFLICT DO NOTHING RETURNING {col_list}"
    )
    out: list[TableRow] = list(cur.fetchall())
    # ON COMMIT DELETE ROWS only fires at commit: a second insert in this transaction
    # must not see these rows again.
    cur.execute(f"TRUNCATE {tmp}")
    return out


# PostgreSQL's binary COPY framing: signature, flags, header extension; the end marker.
_PG_BINARY_HEADER = b"PGCOPY\n\xff\r\n\x00" + b"\x00\x00\x00\x00" * 2
_PG_BINARY_TRAILER = b"\xff\xff"
_NULL = b"\xff\xff\xff\xff"
_F8 = struct.Struct(">id").pack
_RAW_FRAME = struct.Struct(">hiiidiqihi").pack  # 5 fields: int4, float8, int8, int2, bytea
_MEASUREMENT = struct.Struct(">hii" + "id" * 5).pack  # 6 fields: int4, 5 x float8
_MEASUREMENT_KEY = struct.Struct(">hiiid").pack

# The rows of the tables COPYed in binary, as their columns are: (unit_id, ts, can_id, seq,
# data) and (unit_id, ts, v12, v24, i12, i24).
RawRecentRow = tuple[int, float, int, int, bytes]
MeasurementRow = tuple[int, float, float | None, float | None, float | None, float | None]


def _raw_frames_binary(rows: Sequence[TableRow]) -> bytes:
    """raw_recent rows (unit_id, ts, can_id, seq, data) as binary COPY tuples."""
    frames = cast("Sequence[RawRecentRow]", rows)
    return b"".join(
        [_RAW_FRAME(5, 4, u, 8, ts, 8, cid, 2, seq, len(d)) + d for u, ts, cid, seq, d in frames]
    )


def _measurements_binary(rows: Sequence[TableRow]) -> bytes:
    """measurements rows (unit_id, ts, v12, v24, i12, i24; the values nullable)."""
    out = []
    for u, ts, a, b, c, d in cast("Sequence[MeasurementRow]", rows):
        if a is None or b is None or c is None or d is None:
            out.append(
                _MEASUREMENT_KEY(6, 4, u, 8, ts)
                + b"".join([_NULL if v is None else _F8(8, v) for v in (a, b, c, d)])
            )
        else:
            out.append(_MEASUREMENT(6, 4, u, 8, ts, 8, a, 8, b, 8, c, 8, d))
    return b"".join(out)


# Tables whose rows are packed here in binary COPY format: the biggest ones, whose
# columns are fixed-width numbers (plus the frame bytes). A float goes over as its 8 bytes,
# so what is stored is the value decoded, to the bit, without a text round trip; and the
# packing costs a fraction of the driver's per-value adaptation (`Copy.write_row`).
_BINARY_COPY: dict[str, Callable[[Sequence[TableRow]], bytes]] = {
    "raw_recent": _raw_frames_binary,
    "measurements": _measurements_binary,
}
_BINARY_CHUNK_ROWS = 8192


def _copy_rows(
    cur: psycopg.Cursor[TupleRow],
    target: str,
    table: CoreTable,
    cols: list[str],
    params: list[TableRow],
) -> None:
    """COPY `params` (tuples in `cols` order) into `target`, a table shaped like `table`."""
    col_list = ", ".join(cols)
    encode = _BINARY_COPY.get(table.name)
    if encode is None:
        with cur.copy(f"COPY {target} ({col_list}) FROM STDIN") as copy:
            write = copy.write_row
            for p in params:
                write(p)
        return
    with cur.copy(f"COPY {target} ({col_list}) FROM STDIN (FORMAT BINARY)") as copy:
        copy.write(_PG_BINARY_HEADER)
        for i in range(0, len(params), _BINARY_CHUNK_ROWS):
            copy.write(encode(params[i : i + _BINARY_CHUNK_ROWS]))
        copy.write(_PG_BINARY_TRAILER)


RollupKey = tuple[int, str, int, float]
# The rows the rollups count, of the columns asked for (unit_id, ts, *MEASUREMENT_METRICS) and
# (unit_id, ts, battery, *BATTERY_METRICS), a value None where the row has none.
MeasurementRollupRow = tuple[int, float, *tuple[float | None, ...]]
BatteryRollupRow = tuple[int, float, str | None, *tuple[float | None, ...]]
# The rows are grouped by (unit, minute) and (unit, minute, battery).
GroupKey = TypeVar("GroupKey", tuple[int, float], tuple[int, float, str | None])


def _minute(ts: float) -> float:
    return math.floor(ts / 60.0) * 60.0


def _fold(
    out: dict[RollupKey, list[float]],
    groups: Mapping[GroupKey, Sequence[Sequence[float | str | None]]],
    names: Callable[[GroupKey], Sequence[str]],
    first: int,
) -> None:
    """Per (unit, minute[, battery]) group: count, sum, min and max of each metric column
    (columns from `first` on), summed in row order as one running total would."""
    for gkey, rows in groups.items():
        uid, bucket = gkey[0], gkey[1]
        columns = list(zip(*rows, strict=True))[first:]
        for name, column in zip(names(gkey), columns, strict=True):
            values = [v for v in column if v is not None]
            if values:
                out[(uid, name, 60, bucket)] = [len(values), sum(values), min(values), max(values)]


def rollup_deltas(
    measurement_rows: Iterable[MeasurementRollupRow], battery_rows: Iterable[BatteryRollupRow]
) -> dict[RollupKey, list[float]]:
    """(unit, metric, width, bucket start) -> [count, sum, min, max] of newly inserted rows.

    Measurement rows are (unit_id, ts, *MEASUREMENT_METRICS), battery rows (unit_id, ts,
    battery, *BATTERY_METRICS); a per-battery metric gets the battery as suffix (soc_12v)."""
    minute: dict[RollupKey, list[float]] = {}
    m_groups: dict[tuple[int, float], list[MeasurementRollupRow]] = {}
    for m_row in measurement_rows:
        m_key = (m_row[0], _minute(m_row[1]))
        m_group = m_groups.get(m_key)
        if m_group is None:
            m_groups[m_key] = [m_row]
        else:
            m_group.append(m_row)
    _fold(minute, m_groups, lambda _k: MEASUREMENT_METRICS, 2)
    b_groups: dict[tuple[int, float, str | None], list[BatteryRollupRow]] = {}
    for b_row in battery_rows:
        b_key = (b_row[0], _minute(b_row[1]), b_row[2])
        b_group = b_groups.get(b_key)
        if b_group is None:
            b_groups[b_key] = [b_row]
        else:
            b_group.append(b_row)
    _fold(minute, b_groups, _battery_names, 3)
    out = dict(minute)
    for (uid, metric, _, bucket), (count, total, lo, hi) in minute.items():
        for width in BUCKETS_S[1:]:
            wkey = (uid, metric, width, math.floor(bucket / width) * width)
            cur = out.get(wkey)
            if cur is None:
                out[wkey] = [count, total, lo, hi]
            else:
                cur[0] += count
                cur[1] += total
                cur[2] = min(cur[2], lo)
                cur[3] = max(cur[3], hi)
    return out


def _battery_names(gkey: tuple[int, float, str | None]) -> tuple[str, ...]:
    battery = gkey[2]
    if battery is None:
        return BATTERY_METRICS
    return tuple(m if m == "temperature_c" else f"{m}_{battery}" for m in BATTERY_METRICS)


_ROLLUP_KEY = ("unit_id", "bucket_s", "bucket_ts")
# Every non-key column of `rollups`, in the table's order, and each metric's place in a row.
_ROLLUP_VALUE_COLS = [c.name for c in table_of(Rollup).columns if c.name not in _ROLLUP_KEY]
_ROLLUP_AT = {
    m: tuple(_ROLLUP_VALUE_COLS.index(c) for c in rollup_columns(m)) for m in ROLLUP_METRICS
}
_ROLLUP_COLS = ", ".join([*_ROLLUP_KEY, *_ROLLUP_VALUE_COLS])


def _rollup_merge() -> str:
    """Counts and sums add, min and max widen, each metric on its own; a metric the bucket
    or the delta lacks (null) takes the other's. CASE and COALESCE rather than LEAST/min():
    the same SQL on PostgreSQL and SQLite."""
    sets = []
    for m in ROLLUP_METRICS:
        n, total, lo, hi = rollup_columns(m)
        for c in (n, total):
            sets.append(f"{c} = COALESCE(rollups.{c} + excluded.{c}, rollups.{c}, excluded.{c})")
        sets.append(
            f"{lo} = CASE WHEN excluded.{lo} < rollups.{lo} THEN excluded.{lo} "
            f"ELSE COALESCE(rollups.{lo}, excluded.{lo}) END"
        )
        sets.append(
            f"{hi} = CASE WHEN excluded.{hi} > rollups.{hi} THEN excluded.{hi} "
            f"ELSE COALESCE(rollups.{hi}, excluded.{hi}) END"
        )
    return f"ON CONFLICT ({', '.join(_ROLLUP_KEY)}) DO UPDATE SET " + ", ".join(sets)


_ROLLUP_MERGE = _rollup_merge()
_ROLLUP_PG_TYPES = ", ".join(
    ["%s::int[]", "%s::int[]", "%s::float8[]"]
    + ["%s::int[]" if c.endswith("_n") else "%s::float8[]" for c in _ROLLUP_VALUE_COLS]
)


def _pg_nullable_array(values: Sequence[object]) -> str:
    """pg_array of values some of which are None (NULL): a metric a bucket has none of."""
    return "{" + ",".join("NULL" if v is None else str(v) for v in values) + "}"


def rollup_rows(deltas: dict[RollupKey, list[float]]) -> list[tuple[float | None, ...]]:
    """The deltas as rows of `rollups` (a row per unit, width and bucket, every metric's
    columns), in key order."""
    rows: dict[tuple[int, int, float], list[float | None]] = {}
    empty: list[float | None] = [None] * len(_ROLLUP_VALUE_COLS)
    for (uid, metric, width, bucket), (count, total, lo, hi) in deltas.items():
        at = _ROLLUP_AT.get(metric)
        if at is None:  # no such field on the bus (a battery named otherwise): no reader
            continue
        key = (uid, width, float(bucket))
        row = rows.get(key)
        if row is None:
            row = rows[key] = list(empty)
        row[at[0]] = int(count)
        row[at[1]] = float(total)
        row[at[2]] = float(lo)
        row[at[3]] = float(hi)
    return [(*key, *rows[key]) for key in sorted(rows)]


def upsert_rollups(conn: Connection, deltas: dict[RollupKey, list[float]]) -> int:
    """Merge deltas into the rollups: counts and sums add, min and max widen. Returns the
    (metric, bucket) pairs merged.

    Plain tuples through the driver, in key order (writers that touch the same buckets
    lock them in the same order); on PostgreSQL one INSERT ... SELECT from arrays."""
    rows = rollup_rows(deltas)
    if not rows:
        return 0
    raw = conn.connection.driver_connection
    assert raw is not None
    if conn.dialect.name != "postgresql":
        marks = ", ".join("?" * len(rows[0]))
        raw.executemany(
            f"INSERT INTO rollups ({_ROLLUP_COLS}) VALUES ({marks}) " + _ROLLUP_MERGE, rows
        )
        return len(deltas)
    with raw.cursor() as cur:
        cur.execute(
            f"INSERT INTO rollups ({_ROLLUP_COLS}) SELECT * FROM unnest({_ROLLUP_PG_TYPES}) "
            + _ROLLUP_MERGE,
            [_pg_nullable_array(column) for column in zip(*rows, strict=True)],
        )
    return len(deltas)


def _upsert_episodes(
    conn: Connection, episodes: dict[EpisodeKey, EpisodeValues], ids: dict[UnitKey, int]
) -> None:
    if not episodes:
        return
    ins = dialect_insert(conn, _episodes)
    mutable = ("source", "state", "last_seen_at", "ended_at", "ended_by", "occurrence_count")
    stmt = ins.on_conflict_do_update(
        index_elements=["unit_id", "fault", "started_at"],
        set_={c: ins.excluded[c] for c in mutable},
    )
    conn.execute(
        stmt,
        [{**values, "unit_id": ids[key[0]]} for key, values in episodes.items()],
    )


def _upsert_live(
    conn: Connection, live: dict[LiveKey, LiveValues], ids: dict[UnitKey, int]
) -> None:
    if not live:
        return
    ins = dialect_insert(conn, _live)
    # Only newer data replaces the persisted state: replaying an old log leaves it alone.
    stmt = ins.on_conflict_do_update(
        index_elements=["unit_id", "name"],
        set_={"ts": ins.excluded.ts, "fields": ins.excluded.fields},
        where=_live.c.ts <= ins.excluded.ts,
    )
    conn.execute(
        stmt,
        [
            {"unit_id": ids[key[0]], "name": key[1], "ts": v["ts"], "fields": v["fields"]}
            for key, v in live.items()
        ],
    )


def _update_units(conn: Connection, batch: Batch, ids: dict[UnitKey, int]) -> None:
    u = _units.c
    first: BindParameter[float] = bindparam("first")
    last: BindParameter[float] = bindparam("last")
    if batch.seen:
        stmt = (
            update(_units)
            .where(u.id == bindparam("uid"))
            .values(
                first_seen=case(
                    (u.first_seen.is_(None) | (u.first_seen > first), first),
                    else_=u.first_seen,
                ),
                last_seen=case(
                    (u.last_seen.is_(None) | (u.last_seen < last), last),
                    else_=u.last_seen,
                ),
            )
        )
        conn.execute(
            stmt,
            [{"uid": ids[k], "first": v[0], "last": v[1]} for k, v in batch.seen.items()],
        )
    for key, info in batch.unit_info.items():
        values = {k: v for k, v in info.items() if v is not None and k != "ts"}
        if not values:
            continue
        stmt = update(_units).where(u.id == ids[key]).values(**values)
        ts = info.get("ts")
        if ts is not None:
            # An identification older than the NAME holding the address now was another
            # node's (a log replayed out of order).
            stmt = stmt.where(~_owned_since(ids[key], ts))
        conn.execute(stmt)


def _owned_since(uid: int, ts: float) -> Exists:
    """Whether a NAME took unit `uid`'s address after `ts`."""
    o = _owners.c
    return exists().where(o.unit_id == uid, o.since > ts)


def _record_owners(
    conn: Connection, owners: dict[UnitKey, list[tuple[float, str]]], ids: dict[UnitKey, int]
) -> None:
    """The NAMEs that took the units' addresses: a period each, and on the unit row the
    latest NAME, its identity (series, model, software ID) cleared when the NAME differs
    from the one it had (nothing of the previous node shows for the new one)."""
    if not owners:
        return
    taken = [(ids[key], since, name) for key, seen in owners.items() for since, name in seen]
    conn.execute(
        dialect_insert(conn, _owners).on_conflict_do_nothing(index_elements=["unit_id", "since"]),
        [{"unit_id": uid, "since": since, "name": name} for uid, since, name in taken],
    )
    u = _units.c
    for uid, since, name in taken:
        other = u.name.is_not(None) & (u.name != name)
        conn.execute(
            update(_units)
            .where(u.id == uid, ~_owned_since(uid, since))
            .values(
                name=name,
                series=case((other, None), else_=u.series),
                model=case((other, None), else_=u.model),
                software_id=case((other, None), else_=u.software_id),
            )
        )


def write_batch(conn: Connection, batch: Batch, known_units: dict[UnitKey, int]) -> BatchResult:
    """Write one batch inside the caller's transaction; safe to repeat after a failure."""
    ensure_vehicles(conn, batch.vehicles.values(), update_=False)
    new_ids = ensure_units(conn, batch.units, known_units)
    ids = {**known_units, **new_ids}
    missing = batch.touched_units() - ids.keys()
    if missing:
        raise KeyError(f"rows for units never registered: {sorted(missing)}")
    inserted: dict[str, int] = {}
    # Raw frames of minutes already packed go into their blocks; the others to raw_recent.
    # (store_frames takes the frames' values as plain dicts)
    frames = cast(list[tuple[UnitKey, dict[str, object]]], batch.raw_frames)
    recent, into_blocks = archive.store_frames(conn, frames, ids)
    # Rows of hours packed already merge into their blocks; the others go to their tables.
    m_list, m_late = packed.store_late_rows(conn, packed.MEASUREMENTS, batch.measurements, ids)
    b_list, b_late = packed.store_late_rows(conn, packed.BATTERY_STATES, batch.battery_states, ids)
    lists = (
        (_measurements, m_list),
        (_battery, b_list),
        (_status, batch.status_changes),
        (_dm1, batch.dm1_snapshots),
        (_messages, batch.messages),
        (_raw_recent, recent),
    )
    m_cols = ("unit_id", "ts", *MEASUREMENT_METRICS)
    b_cols = ("unit_id", "ts", "battery", *BATTERY_METRICS)
    # The new rows of m_cols and b_cols, as the driver and the blocks give them back.
    m_rows: list[Sequence[object]]
    b_rows: list[Sequence[object]]
    if conn.dialect.name == "postgresql":
        new = _pg_insert_lists(conn, lists, ids)
        for table, _ in lists:
            inserted[table.name] = len(new.get(table.name, ()))
        m_rows = _pick(_measurements, m_cols, new.get("measurements", []))
        b_rows = _pick(_battery, b_cols, new.get("battery_states", []))
    else:
        m_rows = _insert_returning(conn, _measurements, m_list, ids, m_cols)
        b_rows = _insert_returning(conn, _battery, b_list, ids, b_cols)
        inserted["measurements"] = len(m_rows)
        inserted["battery_states"] = len(b_rows)
        for table, rows in lists[2:]:
            inserted[table.name] = _insert_new(conn, table, rows, ids)
    if m_late or b_late:
        m_rows = [*m_rows, *packed.pick(packed.MEASUREMENTS, m_late, m_cols)]
        b_rows = [*b_rows, *packed.pick(packed.BATTERY_STATES, b_late, b_cols)]
        inserted["measurements"] += len(m_late)
        inserted["battery_states"] += len(b_late)
    # Counted as frames archived, wherever they went.
    inserted["raw_frames"] = inserted.pop(_raw_recent.name, 0) + into_blocks
    deltas = rollup_deltas(
        cast("list[MeasurementRollupRow]", m_rows), cast("list[BatteryRollupRow]", b_rows)
    )
    buckets = upsert_rollups(conn, deltas)
    _upsert_episodes(conn, batch.episodes, ids)
    _upsert_live(conn, batch.live, ids)
    _record_owners(conn, batch.unit_owners, ids)
    _update_units(conn, batch, ids)
    return BatchResult(unit_ids=new_ids, inserted=inserted, rollup_buckets=buckets)


def _pick(table: CoreTable, columns: Sequence[str], rows: list[TableRow]) -> list[Sequence[object]]:
    names = [c.name for c in table.columns]
    pick = itemgetter(*(names.index(c) for c in columns))
    return [pick(r) for r in rows]


def load_unit_ids(conn: Connection) -> dict[UnitKey, int]:
    """Every known unit's id by (bus, source address)."""
    return {(b, s): i for i, b, s in conn.execute(select(_units.c.id, _units.c.bus, _units.c.sa))}
