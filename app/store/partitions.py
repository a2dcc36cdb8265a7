"""Time partitions of the time-series tables on PostgreSQL: which tables, how wide, made ahead,
rows outside every partition adopted later, whole partitions dropped by the retention.

Each table of `TIME_TABLES` is partitioned by RANGE on its float time column; `rollups` is
partitioned by LIST on `bucket_s`, each width (`ROLLUP_SPANS`) by RANGE on `bucket_ts`, so
that each width has its own retention. Partitions live in a schema of their own
(`<schema>_partitions`): the application's schema shows the tables a user queries, and a
schema comparison (Alembic's autogenerate) sees no partitions to drop.

No row is ever refused: every partitioned table has a DEFAULT partition that takes what no
partition covers (a replayed log from 2019, a clock that jumped). `maintain` (run hourly by
one gateway at a time, under a PostgreSQL advisory lock; `eqgw db prune` runs it too) makes
the partitions of the next days ahead and moves the default's rows that are still inside the
retention into partitions of their own; rows of the default older than the retention are
deleted by the retention's batched DELETE (they are the exception). A partition is dropped
once its whole range is older than the cutoff: a row goes between its retention and its
retention plus one partition span (a day for the big tables).

SQLite is left as it is (one file, deletes are cheap there: docs/performance.md). A table that
is not partitioned on PostgreSQL (created by hand, or turned into a TimescaleDB hypertable)
is left alone here and pruned by the DELETE path.
"""

from __future__ import annotations

import logging
import math
import re
import threading
import time
from collections.abc import Callable, Iterator, Mapping
from contextlib import contextmanager
from dataclasses import dataclass, field

from sqlalchemy import Connection, Engine, text
from sqlalchemy.exc import OperationalError

from eqgw.store.engine import db_deadline

log = logging.getLogger(__name__)

DAY_S = 86400
WEEK_S = 7 * DAY_S
# Spans are counted from a Monday, 1970-01-05 00:00 UTC: a week's partition starts on Monday.
ORIGIN_S = 4 * DAY_S
# A maintenance statement waits for a table lock at most this long (a long read holds its
# table): it fails and is tried again next round instead of queueing the writer behind it.
LOCK_TIMEOUT_MS = 5000
# How long a round or a prune waits for another process's round (the advisory lock): a round
# takes a second or two; below the connections' answer deadline (eqgw.store.engine).
LOCK_WAIT_S = 5.0
# Default rows further ahead than this stay in the default (a bogus time, not a clock jump).
ADOPT_AHEAD_S = 400 * DAY_S


@dataclass(frozen=True, slots=True)
class Series:
    """A range-partitioned table: its time column and the width of one partition.
    `nested`: a sub-table of a partitioned table (rollups of one width), in the partitions'
    schema."""

    table: str
    column: str
    span_s: int
    nested: bool = False


# Day partitions for the tables that take rows all day long (a 500-vehicle fleet writes tens of
# millions of measurements a day: a day is the unit of retention worth dropping); week
# partitions for the tables written only on a change (a day's partition would be mostly empty,
# and a week keeps the catalog small: a row goes at most a week after its retention).
TIME_TABLES: dict[str, Series] = {
    s.table: s
    for s in (
        Series("measurements", "ts", DAY_S),
        Series("battery_states", "ts", DAY_S),
        Series("status_changes", "ts", WEEK_S),
        Series("dm1_snapshots", "ts", WEEK_S),
        Series("messages", "ts", WEEK_S),
        Series("raw_blocks", "ts", DAY_S),
        Series("raw_recent", "ts", DAY_S),
        Series("measurement_blocks", "ts", DAY_S),
        Series("battery_blocks", "ts", DAY_S),
    )
}
# Rollup widths (eqgw.store.writes.BUCKETS_S) and the span of their partitions: about 30 of
# each for the default retentions (1 min 30 d, 15 min 1 y, 1 h and 1 d 5 y).
ROLLUP_SPANS: dict[int, int] = {60: DAY_S, 900: WEEK_S, 3600: 8 * WEEK_S, 86400: 52 * WEEK_S}
ROLLUPS = "rollups"
# Tables whose rows move into blocks once their hour is past (eqgw.store.packed): the packing
# deletes them, and a past partition they all left is truncated (`truncate_emptied`).
PACKED_TABLES = ("measurements", "battery_states")


def rollup_series(width_s: int) -> Series:
    """The partitioned sub-table of `rollups` holding the buckets `width_s` wide."""
    return Series(f"{ROLLUPS}_{width_s}", "bucket_ts", ROLLUP_SPANS[width_s], nested=True)


def all_series() -> list[Series]:
    return [*TIME_TABLES.values(), *(rollup_series(w) for w in ROLLUP_SPANS)]


def span_start(t: float, span_s: int) -> float:
    """The start of the span of width `span_s` holding time `t`."""
    return ORIGIN_S + math.floor((t - ORIGIN_S) / span_s) * span_s


@dataclass(frozen=True, slots=True)
class Partition:
    """One partition: its name (in the partitions' schema) and range; lo -inf for a range
    FROM (MINVALUE) (an attached legacy table); a DEFAULT partition has no range."""

    name: str
    lo: float | None
    hi: float | None

    @property
    def default(self) -> bool:
        return self.lo is None


def is_postgres(conn: Connection) -> bool:
    return conn.dialect.name == "postgresql"


def partition_schema(conn: Connection) -> str:
    """The schema holding the partitions of the current schema's tables."""
    return f"{conn.execute(text('SELECT current_schema()')).scalar_one()}_partitions"


def _q(name: str) -> str:
    return '"' + name.replace('"', '""') + '"'


def qualified(conn: Connection, series: Series | str) -> str:
    """A table's quoted, schema-qualified name."""
    name, nested = (series, False) if isinstance(series, str) else (series.table, series.nested)
    schema = (
        partition_schema(conn)
        if nested
        else conn.execute(text("SELECT current_schema()")).scalar_one()
    )
    return f"{_q(schema)}.{_q(name)}"


def is_partitioned(conn: Connection, series: Series | str) -> bool:
    """Whether the table is a partitioned table here (False on SQLite, for a plain table or a
    table that does not exist)."""
    if not is_postgres(conn):
        return False
    return bool(
        conn.execute(
            text(
                "SELECT EXISTS (SELECT 1 FROM pg_partitioned_table "
                "WHERE partrelid = to_regclass(:t))"
            ),
            {"t": qualified(conn, series)},
        ).scalar_one()
    )


_BOUND = re.compile(r"FOR VALUES FROM \((MINVALUE|'[^']*')\) TO \((MAXVALUE|'[^']*')\)")


def _bound(text_: str, infinite: float) -> float:
    return infinite if text_.endswith("VALUE") else float(text_.strip("'"))


def partitions(conn: Connection, series: Series | str) -> list[Partition]:
    """The partitions of a partitioned table, by range (the default last)."""
    rows = conn.execute(
        text(
            "SELECT c.relname, pg_get_expr(c.relpartbound, c.oid) FROM pg_inherits i "
            "JOIN pg_class c ON c.oid = i.inhrelid WHERE i.inhparent = to_regclass(:t)"
        ),
        {"t": qualified(conn, series)},
    ).all()
    out: list[Partition] = []
    for name, bound in rows:
        m = _BOUND.search(bound or "")
        if m is None:
            out.append(Partition(name, None, None))
        else:
            out.append(Partition(name, _bound(m[1], -math.inf), _bound(m[2], math.inf)))
    return sorted(out, key=lambda p: (p.default, p.lo or 0.0))


def default_name(table: str) -> str:
    return f"{table}_default"


def _partition_name(table: str, lo: float) -> str:
    tm = time.gmtime(lo)
    stamp = time.strftime("%Y%m%d", tm)
    if lo % DAY_S:
        stamp += time.strftime("_%H%M%S", tm)
    return f"{table}_p{stamp}"


def _lock_timeout(conn: Connection) -> None:
    conn.execute(text(f"SET LOCAL lock_timeout = {LOCK_TIMEOUT_MS}"))


def create_partitioned(
    conn: Connection, table: str, column: str, *, like: str, primary_key: list[str]
) -> None:
    """Create `table` (in the current schema) partitioned by RANGE on `column`, with the
    columns of table `like`, its primary key named pk_<table>, and a DEFAULT partition: for a
    new time-series table (and the migrations)."""
    conn.execute(
        text(
            f"CREATE TABLE {_q(table)} (LIKE {like} INCLUDING DEFAULTS INCLUDING CONSTRAINTS) "
            f"PARTITION BY RANGE ({_q(column)})"
        )
    )
    cols = ", ".join(_q(c) for c in primary_key)
    conn.execute(
        text(f"ALTER TABLE {_q(table)} ADD CONSTRAINT {_q('pk_' + table)} PRIMARY KEY ({cols})")
    )
    create_default(conn, Series(table, column, DAY_S))


def create_default(conn: Connection, series: Series) -> None:
    """The DEFAULT partition of a partitioned table, with an index on the time column (which
    finds the default's rows of a range at once, for `adopt_default`)."""
    schema = partition_schema(conn)
    conn.execute(text(f"CREATE SCHEMA IF NOT EXISTS {_q(schema)}"))
    name = default_name(series.table)
    conn.execute(
        text(
            f"CREATE TABLE IF NOT EXISTS {_q(schema)}.{_q(name)} "
            f"PARTITION OF {qualified(conn, series)} DEFAULT"
        )
    )
    conn.execute(
        text(
            f"CREATE INDEX IF NOT EXISTS {_q(name + '_' + series.column)} "
            f"ON {_q(schema)}.{_q(name)} ({_q(series.column)})"
        )
    )


def make_partition(
    conn: Connection, series: Series, lo: float, hi: float, *, wait_ms: int | None = LOCK_TIMEOUT_MS
) -> tuple[str, int]:
    """Make the partition [lo, hi) of `series` (trimmed to what no partition covers yet), in
    the caller's transaction; rows of the range held by the default partition are moved into
    it first. Returns (its name, rows moved); ("", 0) when the range was covered already.
    `wait_ms`: how long to wait for a table lock (None: the session's setting)."""
    parts = partitions(conn, series)
    for p in parts:
        if p.lo is None or p.hi is None:
            continue
        if p.lo <= lo < p.hi:
            lo = p.hi
        if lo < p.lo < hi:
            hi = p.lo
    if lo >= hi:
        return "", 0
    if wait_ms is not None:
        conn.execute(text(f"SET LOCAL lock_timeout = {int(wait_ms)}"))
    schema = partition_schema(conn)
    conn.execute(text(f"CREATE SCHEMA IF NOT EXISTS {_q(schema)}"))
    parent = qualified(conn, series)
    name = _partition_name(series.table, lo)
    target = f"{_q(schema)}.{_q(name)}"
    conn.execute(
        text(f"CREATE TABLE {target} (LIKE {parent} INCLUDING DEFAULTS INCLUDING CONSTRAINTS)")
    )
    moved = 0
    col = _q(series.column)
    default = next((p for p in parts if p.default), None)
    if default is not None:
        source = f"{_q(schema)}.{_q(default.name)}"
        # The default is held from here to the commit (ATTACH would take it anyway): a row a
        # writer adds to it meanwhile cannot slip in between the move and the attach.
        conn.execute(text(f"LOCK TABLE {source} IN ACCESS EXCLUSIVE MODE"))
        where = f"{col} >= :lo AND {col} < :hi"
        # A replayed month may leave days of a fleet in the default: the move takes as long
        # as it takes (no statement deadline), or it would fail the same way every round.
        with db_deadline(None):
            conn.execute(text("SET LOCAL statement_timeout = 0"))
            moved = conn.execute(
                text(f"INSERT INTO {target} SELECT * FROM {source} WHERE {where}"),
                {"lo": lo, "hi": hi},
            ).rowcount
            if moved:
                conn.execute(text(f"DELETE FROM {source} WHERE {where}"), {"lo": lo, "hi": hi})
    conn.execute(
        text(
            f"ALTER TABLE {parent} ATTACH PARTITION {target} "
            f"FOR VALUES FROM ('{lo!r}') TO ('{hi!r}')"
        )
    )
    return name, max(moved, 0)


@dataclass(slots=True)
class MaintainResult:
    """What a maintenance round did: partitions made, rows moved out of default partitions;
    `skipped` when another process held the lock."""

    made: list[str] = field(default_factory=list)
    moved: int = 0
    skipped: bool = False
    truncated: list[str] = field(default_factory=list)


LOCK_SQL = (
    "hashtextextended('eqgw-partitions/' || current_database() || '/' || current_schema(), 0)"
)


@contextmanager
def partition_lock(conn: Connection, wait_s: float = 0.0) -> Iterator[bool]:
    """The session advisory lock that lets one process at a time make or drop partitions of
    this schema (several gateways may share the database); yields whether it was taken,
    waiting for it at most `wait_s` (another gateway's round takes a second or so: waiting
    keeps two periodic loops from skipping each other's turn forever)."""
    if wait_s <= 0:
        got = bool(conn.execute(text(f"SELECT pg_try_advisory_lock({LOCK_SQL})")).scalar_one())
        conn.commit()
    else:
        try:
            with db_deadline(wait_s + 5.0):
                conn.execute(text(f"SET LOCAL lock_timeout = {int(wait_s * 1000)}"))
                conn.execute(text(f"SET LOCAL statement_timeout = {int(wait_s * 1000) + 5000}"))
                conn.execute(text(f"SELECT pg_advisory_lock({LOCK_SQL})"))
            conn.commit()
            got = True
        except OperationalError as exc:  # lock_not_available: another holds it still
            conn.rollback()
            if getattr(exc.orig, "sqlstate", None) != "55P03":
                raise
            got = False
    try:
        yield got
    finally:
        if got:
            conn.execute(text(f"SELECT pg_advisory_unlock({LOCK_SQL})"))
            conn.commit()


def keep_from(
    series: Series, now: float, raw_days: float, rollup_days: Mapping[int, float]
) -> float:
    """The retention's cutoff of a series: rows older are pruned, not adopted."""
    if series.nested:
        width = int(series.table.rsplit("_", 1)[1])
        return now - rollup_days[width] * DAY_S
    return now - raw_days * DAY_S


def maintain(
    engine: Engine,
    *,
    raw_days: float,
    rollup_days: Mapping[int, float],
    ahead_days: float = 3.0,
    now: float | None = None,
    stop: threading.Event | None = None,
    lock_wait_s: float = LOCK_WAIT_S,
    adopt: bool = True,
) -> MaintainResult:
    """One maintenance round (PostgreSQL; nothing on SQLite): the partitions from yesterday
    to `ahead_days` ahead made, and the default partitions' rows inside the retention moved
    into partitions of their own (unless not `adopt`). Each partition in its own transaction;
    once `stop` is set, the round ends after the partition at hand (the next round goes on
    from there).

    A move is not invisible to readers: a statement whose snapshot predates the move's commit
    but that plans after it may miss the moved rows (the default no longer covers their
    range, their new partition is too new for its snapshot). The gateway's keeper therefore
    adopts nothing (it only moves the rare rows a clock ahead put in a range it makes);
    `eqgw db prune` adopts."""
    result = MaintainResult()
    if engine.dialect.name != "postgresql":
        return result
    now = time.time() if now is None else now
    with engine.connect() as conn, partition_lock(conn, lock_wait_s) as mine:
        if not mine:
            result.skipped = True
            return result
        for series in all_series():
            if stop is not None and stop.is_set():
                break
            partitioned = is_partitioned(conn, series)
            conn.commit()
            if not partitioned:
                continue
            start = span_start(now - DAY_S, series.span_s)
            while start < now + ahead_days * DAY_S and not (stop is not None and stop.is_set()):
                _make(conn, series, start, start + series.span_s, result)
                start += series.span_s
            if adopt:
                adopt_default(
                    conn,
                    series,
                    keep_from(series, now, raw_days, rollup_days),
                    now + ADOPT_AHEAD_S,
                    result,
                )
            if series.table in PACKED_TABLES:
                truncate_emptied(conn, series, now, result)
    return result


def truncate_emptied(
    conn: Connection, series: Series, before: float, result: MaintainResult
) -> None:
    """Truncate the partitions of `series` that ended before `before` and whose rows were
    all packed away: the packing's DELETEs left their space to VACUUM (every row a dead
    tuple); TRUNCATE gives it back at once and leaves none. A partition qualifies by the
    statistics (no live row, some storage), and is checked empty again under its exclusive
    lock (a late row may have come meanwhile), waited for at most LOCK_TIMEOUT_MS; one that
    is busy is left to the next round. TRUNCATE is not MVCC-safe: a transaction whose
    snapshot predates the packing's commit would read the partition empty; the gateway reads
    in READ COMMITTED, where each statement sees the blocks the rows went into."""
    schema = partition_schema(conn)
    due = [p for p in partitions(conn, series) if not p.default and (p.hi or math.inf) <= before]
    for p in due:
        target = f"{_q(schema)}.{_q(p.name)}"
        row = conn.execute(
            text(
                "SELECT pg_relation_size(c.oid), s.n_live_tup FROM pg_class c "
                "LEFT JOIN pg_stat_user_tables s ON s.relid = c.oid WHERE c.oid = to_regclass(:t)"
            ),
            {"t": target},
        ).first()
        conn.commit()
        if row is None or not row[0] or row[1]:
            continue
        # Unlocked first: the scan that proves it empty is not made under the lock (and it
        # prunes the pages, so the check under the lock reads them quickly).
        held = conn.execute(text(f"SELECT EXISTS (SELECT 1 FROM {target})")).scalar_one()
        conn.commit()
        if held:
            continue
        try:
            with conn.begin():
                _lock_timeout(conn)
                conn.execute(text(f"LOCK TABLE {target} IN ACCESS EXCLUSIVE MODE"))
                if conn.execute(text(f"SELECT EXISTS (SELECT 1 FROM {target})")).scalar_one():
                    continue
                conn.execute(text(f"TRUNCATE {target}"))
        except OperationalError as exc:  # lock_not_available: a long read holds it
            if getattr(exc.orig, "sqlstate", None) != "55P03":
                raise
            log.info("partition %s busy: truncated next round", p.name)
            continue
        result.truncated.append(p.name)
        log.info("partition %s truncated (every row packed)", p.name)


def _make(conn: Connection, series: Series, lo: float, hi: float, result: MaintainResult) -> float:
    """make_partition in a transaction of its own; returns the end of the range handled."""
    with conn.begin():
        name, moved = make_partition(conn, series, lo, hi)
    if name:
        result.made.append(name)
        result.moved += moved
        log.info("partition %s made (%d rows moved from the default)", name, moved)
    return hi


def adopt_default(
    conn: Connection, series: Series, lo: float, hi: float, result: MaintainResult
) -> None:
    """Move the rows of `series`' default partition with lo <= time < hi into partitions of
    their own (made for the spans that hold them)."""
    schema = partition_schema(conn)
    source = f"{_q(schema)}.{_q(default_name(series.table))}"
    col = _q(series.column)
    exists = conn.execute(text("SELECT to_regclass(:t) IS NOT NULL"), {"t": source}).scalar_one()
    conn.commit()
    if not exists:
        return
    cursor = lo
    while True:
        first = conn.execute(
            text(f"SELECT min({col}) FROM {source} WHERE {col} >= :lo AND {col} < :hi"),
            {"lo": cursor, "hi": hi},
        ).scalar_one_or_none()
        conn.commit()
        if first is None:
            return
        start = span_start(float(first), series.span_s)
        end = start + series.span_s
        _make(conn, series, start, end, result)
        cursor = end


@dataclass(frozen=True, slots=True)
class Dropped:
    """A partition dropped by the retention and about how many rows it held."""

    name: str
    rows: int


def drop_before(
    conn: Connection,
    series: Series,
    cutoff: float,
    *,
    on_drop: Callable[[Connection], None] | None = None,
) -> list[Dropped]:
    """Drop the partitions of `series` whose whole range is older than `cutoff`, each in a
    transaction of its own (the caller holds `partition_lock`); `on_drop(conn)` runs in each
    drop's transaction. Rows are counted from the
    planner's statistics when the partition has any (counting a day of a fleet would cost a
    scan), else exactly."""
    schema = partition_schema(conn)
    due = [p for p in partitions(conn, series) if p.hi is not None and p.hi <= cutoff]
    conn.commit()
    out: list[Dropped] = []
    for p in due:
        target = f"{_q(schema)}.{_q(p.name)}"
        with conn.begin():
            _lock_timeout(conn)
            estimate = conn.execute(
                text("SELECT reltuples FROM pg_class WHERE oid = to_regclass(:t)"), {"t": target}
            ).scalar_one()
            rows = (
                int(estimate)
                if estimate is not None and estimate >= 0
                else int(conn.execute(text(f"SELECT count(*) FROM {target}")).scalar_one())
            )
            conn.execute(text(f"DROP TABLE {target}"))
            if on_drop is not None:
                on_drop(conn)
        out.append(Dropped(p.name, rows))
        log.info("partition %s dropped (about %d rows)", p.name, rows)
    conn.commit()
    return out
