"""Retention: raw rows older than N days, rollups of each width older than their own retention.

On PostgreSQL the time-series tables are partitioned by time (eqgw.store.partitions): a
partition whose whole range is past the cutoff is dropped (milliseconds, nothing left for
VACUUM), under the advisory lock that lets one process at a time change partitions; the rows
of the DEFAULT partitions (times no partition covered) are deleted in batches. So a row goes
between its retention and its retention plus one partition span (a day for the big tables).

On SQLite (and for a table that is not partitioned) rows are deleted in batches along each
unit's primary key (unit_id, ts, ...): every batch is its own short transaction, so the
ingest's writer is never held up for long (SQLite has one writer lock; PostgreSQL locks only
the deleted rows). Fault episodes and the webhook delivery log are always deleted row by row.
See docs/storage.md.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Iterator, Mapping
from contextlib import contextmanager
from contextvars import ContextVar
from dataclasses import dataclass, field

from sqlalchemy import Connection, Engine, MetaData, delete, select, text
from sqlalchemy.sql.elements import ColumnElement

from eqgw.store import partitions as parts
from eqgw.store.archive import BLOCK_S
from eqgw.store.models import (
    RAW_TABLES,
    CoreTable,
    FaultEpisode,
    Rollup,
    RollupDeletion,
    Unit,
    table_of,
)
from eqgw.store.packed import BLOCK_SPAN_S
from eqgw.store.webhook_models import WebhookDelivery
from eqgw.store.writes import dialect_insert

DAY_S = 86400.0

_units = table_of(Unit)
_rollups = table_of(Rollup)
_rollup_deletions = table_of(RollupDeletion)
_episodes = table_of(FaultEpisode)
_deliveries = table_of(WebhookDelivery)


@dataclass(slots=True)
class PruneResult:
    """Rows deleted per table (a dropped partition's rows as the planner's statistics count
    them), how many transactions it took, and the partitions dropped per table."""

    deleted: dict[str, int] = field(default_factory=dict)
    batches: int = 0
    dropped: dict[str, list[str]] = field(default_factory=dict)
    stopped: bool = False  # asked to stop (`prune(stop=...)`): ended before the rest

    @property
    def total(self) -> int:
        return sum(self.deleted.values())


class _Stopped(Exception):
    """A prune asked to stop ends here, between two transactions."""


# The running prune's stop (the prune's own thread: `prune` sets it for its calls).
_stop: ContextVar[threading.Event | None] = ContextVar("eqgw_prune_stop", default=None)


def _go_on() -> None:
    """Before a transaction: end the prune here if it was asked to stop."""
    stop = _stop.get()
    if stop is not None and stop.is_set():
        raise _Stopped


def _prune_table(
    engine: Engine,
    table: CoreTable,
    time_col: str,
    cutoff: float,
    unit_ids: list[int],
    batch_rows: int,
    result: PruneResult,
    pause_s: float,
    on_deleted: Callable[[Connection, int], None] | None = None,
    where: ColumnElement[bool] | None = None,
    name: str | None = None,
) -> None:
    """Delete a table's rows older than `cutoff` (and matching `where`), unit by unit,
    `batch_rows` a transaction; `on_deleted(conn, unit_id)` runs in the transaction of each
    batch that deleted rows. `name`: the table the count goes to (default: this one's)."""
    ts = table.c[time_col]
    uid = table.c.unit_id
    extra = [] if where is None else [where]
    for unit in unit_ids:
        while True:
            _go_on()
            with engine.begin() as conn:
                # The batch's upper bound in time: the primary key index gives it cheaply, and
                # the same DELETE works on both engines (no DELETE ... LIMIT on PostgreSQL).
                edge = conn.execute(
                    select(ts)
                    .where(uid == unit, ts < cutoff, *extra)
                    .order_by(ts)
                    .offset(batch_rows - 1)
                    .limit(1)
                ).scalar_one_or_none()
                cond = ts < cutoff if edge is None else ts <= edge
                n = conn.execute(delete(table).where(uid == unit, cond, *extra)).rowcount
                if n and on_deleted is not None:
                    on_deleted(conn, unit)
            result.batches += 1
            key = name or table.name
            result.deleted[key] = result.deleted.get(key, 0) + max(n, 0)
            if edge is None:
                break
            if pause_s:
                time.sleep(pause_s)  # let the writer in between batches


def prune(
    engine: Engine,
    *,
    raw_days: float,
    rollup_days: float,
    rollup_days_by_width: Mapping[int, float] | None = None,
    now: float | None = None,
    batch_rows: int = 5000,
    pause_s: float = 0.0,
    lock_wait_s: float = parts.LOCK_WAIT_S,
    stop: threading.Event | None = None,
) -> PruneResult:
    """Delete raw rows older than `raw_days`; rollups older than their width's retention
    (`rollup_days_by_width`, else `rollup_days`); closed episodes and finished webhook
    deliveries (the delivery log) older than `rollup_days`. Once `stop` is set, the prune
    ends before its next transaction (`stopped` in the result; the next prune goes on)."""
    result = PruneResult()
    with _until_stopped(stop, result):
        now = time.time() if now is None else now
        # SQLite: take the write lock at BEGIN, as the writer does (see eqgw.store.engine).
        engine = engine.execution_options(sqlite_begin="IMMEDIATE")
        raw_cutoff = now - raw_days * DAY_S
        rollup_cutoff = now - rollup_days * DAY_S
        widths = dict(rollup_days_by_width or {})
        with engine.connect() as conn:
            unit_ids = list(conn.execute(select(_units.c.id).order_by(_units.c.id)).scalars())
        with _partition_lock(engine, lock_wait_s) as (conn, mine):
            for table in RAW_TABLES:
                _go_on()
                # A block of the raw archive goes once its last possible frame is past the cutoff.
                cut = raw_cutoff - {"raw_blocks": BLOCK_S, **BLOCK_SPAN_S}.get(table.name, 0.0)
                series = parts.TIME_TABLES.get(table.name)
                if conn is None or series is None or not _partitioned(conn, series):
                    _prune_table(engine, table, "ts", cut, unit_ids, batch_rows, result, pause_s)
                    continue
                if mine:  # else another process drops partitions now; next round does
                    _drop(conn, series, table.name, cut, result)
                default = _default_of(conn, table)
                if _holds_older(conn, default, "ts", cut):
                    _prune_table(
                        engine,
                        default,
                        "ts",
                        cut,
                        unit_ids,
                        batch_rows,
                        result,
                        pause_s,
                        name=table.name,
                    )
            _prune_rollups(
                engine,
                conn,
                mine,
                rollup_cutoff,
                widths,
                now,
                unit_ids,
                batch_rows,
                result,
                pause_s,
            )
        _go_on()
        with engine.begin() as conn:
            n = conn.execute(
                delete(_episodes).where(
                    _episodes.c.state == "closed", _episodes.c.ended_at < rollup_cutoff
                )
            ).rowcount
            result.deleted[_episodes.name] = max(n, 0)
            result.batches += 1
        _go_on()
        with engine.begin() as conn:
            # Pending deliveries stay whatever their age: the outbox never drops an event.
            n = conn.execute(
                delete(_deliveries).where(
                    _deliveries.c.state.in_(("delivered", "failed")),
                    _deliveries.c.created_at < rollup_cutoff,
                )
            ).rowcount
            result.deleted[_deliveries.name] = max(n, 0)
            result.batches += 1
    return result


@contextmanager
def _until_stopped(stop: threading.Event | None, result: PruneResult) -> Iterator[None]:
    """The prune's body with `stop` where `_go_on` looks, before each transaction; a stop
    ends the body there (`result.stopped`)."""
    token = _stop.set(stop)
    try:
        yield
    except _Stopped:
        result.stopped = True
    finally:
        _stop.reset(token)


def bump_rollup_generation(conn: Connection, unit_id: int) -> None:
    """Count a deletion of `unit_id`'s rollups, in the deleting transaction: a reader that
    holds rollups of the unit (eqgw.store.history_cache) reads them again."""
    ins = dialect_insert(conn, _rollup_deletions)
    conn.execute(
        ins.values(unit_id=unit_id, generation=1, last_at=time.time()).on_conflict_do_update(
            index_elements=["unit_id"],
            set_={
                "generation": _rollup_deletions.c.generation + 1,
                "last_at": ins.excluded.last_at,
            },
        )
    )


@contextmanager
def _partition_lock(engine: Engine, wait_s: float) -> Iterator[tuple[Connection | None, bool]]:
    """On PostgreSQL, a connection and whether it holds the partitions' advisory lock (when
    another process holds it, that one changes partitions: only rows of the DEFAULT
    partitions are deleted); (None, False) on SQLite."""
    if engine.dialect.name != "postgresql":
        yield None, False
        return
    with engine.connect() as conn, parts.partition_lock(conn, wait_s) as mine:
        yield conn, mine


def _partitioned(conn: Connection, series: parts.Series | str) -> bool:
    got = parts.is_partitioned(conn, series)
    conn.commit()
    return got


def _drop(
    conn: Connection,
    series: parts.Series,
    name: str,
    cutoff: float,
    result: PruneResult,
    on_drop: Callable[[Connection], None] | None = None,
) -> list[parts.Dropped]:
    dropped = parts.drop_before(conn, series, cutoff, on_drop=on_drop)
    for d in dropped:
        result.batches += 1
        result.deleted[name] = result.deleted.get(name, 0) + d.rows
        result.dropped.setdefault(name, []).append(d.name)
    result.deleted.setdefault(name, 0)
    return dropped


def _default_of(conn: Connection, table: CoreTable) -> CoreTable:
    """The DEFAULT partition of a partitioned table, as a Core table of the same columns."""
    schema = parts.partition_schema(conn)
    conn.commit()
    return table.to_metadata(MetaData(), schema=schema, name=parts.default_name(table.name))


def _holds_older(conn: Connection, table: CoreTable, time_col: str, cutoff: float) -> bool:
    """Whether `table` (a default partition: its time column is indexed) has a row older than
    `cutoff`: most of the time it has none, and its unit-by-unit walk is skipped."""
    ts = table.c[time_col]
    found = conn.execute(select(ts).where(ts < cutoff).limit(1)).first() is not None
    conn.commit()
    return found


def _prune_rollups(
    engine: Engine,
    conn: Connection | None,
    mine: bool,
    default_cutoff: float,
    widths: dict[int, float],
    now: float,
    unit_ids: list[int],
    batch_rows: int,
    result: PruneResult,
    pause_s: float,
) -> None:
    """Each width's rollups older than its own retention: its partitions dropped, or deleted."""
    name = _rollups.name
    b = _rollups.c.bucket_s
    partitioned = conn is not None and _partitioned(conn, name)
    cutoffs = {
        w: now - widths[w] * DAY_S if w in widths else default_cutoff
        for w in sorted(set(widths) | set(parts.ROLLUP_SPANS))
    }
    if conn is None or not partitioned:
        if all(c == default_cutoff for c in cutoffs.values()):
            cutoffs = {}  # one pass over every width
        for width, cutoff in cutoffs.items():
            _prune_table(
                engine,
                _rollups,
                "bucket_ts",
                cutoff,
                unit_ids,
                batch_rows,
                result,
                pause_s,
                on_deleted=bump_rollup_generation,
                where=b == width,
            )
        _prune_table(
            engine,
            _rollups,
            "bucket_ts",
            default_cutoff,
            unit_ids,
            batch_rows,
            result,
            pause_s,
            on_deleted=bump_rollup_generation,
            where=b.not_in(list(cutoffs)) if cutoffs else None,
        )
        result.deleted.setdefault(name, 0)
        return

    def prune_default(
        of: str,
        cutoff: float,
        *,
        width: int | None = None,
        other_than: list[int] | None = None,
        look_first: bool = True,
    ) -> None:
        """Delete the rollups older than `cutoff` from `of`'s DEFAULT partition: of one
        `width` or of every width but `other_than`, else all. `look_first`: skip the walk when
        the partition holds no row older than the cutoff."""
        default = _rollups.to_metadata(
            MetaData(), schema=parts.partition_schema(conn), name=parts.default_name(of)
        )
        conn.commit()
        if look_first and not _holds_older(conn, default, "bucket_ts", cutoff):
            return
        where: ColumnElement[bool] | None = None
        if width is not None:
            where = default.c.bucket_s == width
        elif other_than is not None:
            where = default.c.bucket_s.not_in(other_than)
        _prune_table(
            engine,
            default,
            "bucket_ts",
            cutoff,
            unit_ids,
            batch_rows,
            result,
            pause_s,
            on_deleted=bump_rollup_generation,
            name=name,
            where=where,
        )

    for width, cutoff in cutoffs.items():
        if width not in parts.ROLLUP_SPANS:  # in the LIST default partition
            prune_default(name, cutoff, width=width, look_first=False)
            continue
        series = parts.rollup_series(width)
        if mine:
            # Every unit's rollups may have been in a dropped partition.
            _drop(conn, series, name, cutoff, result, on_drop=_bump_all)
        prune_default(series.table, cutoff)
    # Widths without a partition of their own (none today) and no retention of their own.
    prune_default(name, default_cutoff, other_than=list(cutoffs))
    result.deleted.setdefault(name, 0)


def _bump_all(conn: Connection) -> None:
    """bump_rollup_generation for every unit, in one statement."""
    conn.execute(
        text(
            "INSERT INTO rollup_deletions (unit_id, generation, last_at) "
            "SELECT id, 1, :now FROM units ON CONFLICT (unit_id) DO UPDATE SET "
            "generation = rollup_deletions.generation + 1, last_at = excluded.last_at"
        ),
        {"now": time.time()},
    )
