"""Retention: delete raw rows older than N days and rollups older than M days, in small batches.

Both engines delete in batches along each unit's primary key (unit_id, ts, ...): every batch is
its own short transaction, so the ingest's writer is never held up for long (SQLite has one
writer lock; PostgreSQL locks only the deleted rows). See docs/storage.md for why PostgreSQL
does not partition.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field

from sqlalchemy import Connection, Engine, Table, delete, select

from eqgw.store.archive import BLOCK_S
from eqgw.store.models import RAW_TABLES, FaultEpisode, Rollup, RollupDeletion, Unit
from eqgw.store.packed import BLOCK_SPAN_S
from eqgw.store.webhook_models import WebhookDelivery
from eqgw.store.writes import dialect_insert

DAY_S = 86400.0

_units: Table = Unit.__table__  # type: ignore[assignment]
_rollups: Table = Rollup.__table__  # type: ignore[assignment]
_rollup_deletions: Table = RollupDeletion.__table__  # type: ignore[assignment]
_episodes: Table = FaultEpisode.__table__  # type: ignore[assignment]
_deliveries: Table = WebhookDelivery.__table__  # type: ignore[assignment]


@dataclass(slots=True)
class PruneResult:
    """Rows deleted per table, and how many transactions it took."""

    deleted: dict[str, int] = field(default_factory=dict)
    batches: int = 0

    @property
    def total(self) -> int:
        return sum(self.deleted.values())


def _prune_table(
    engine: Engine,
    table: Table,
    time_col: str,
    cutoff: float,
    unit_ids: list[int],
    batch_rows: int,
    result: PruneResult,
    pause_s: float,
    on_deleted: Callable[[Connection, int], None] | None = None,
) -> None:
    """Delete a table's rows older than `cutoff`, unit by unit, `batch_rows` a transaction;
    `on_deleted(conn, unit_id)` runs in the transaction of each batch that deleted rows."""
    ts = table.c[time_col]
    uid = table.c.unit_id
    for unit in unit_ids:
        while True:
            with engine.begin() as conn:
                # The batch's upper bound in time: the primary key index gives it cheaply, and
                # the same DELETE works on both engines (no DELETE ... LIMIT on PostgreSQL).
                edge = conn.execute(
                    select(ts)
                    .where(uid == unit, ts < cutoff)
                    .order_by(ts)
                    .offset(batch_rows - 1)
                    .limit(1)
                ).scalar_one_or_none()
                cond = ts < cutoff if edge is None else ts <= edge
                n = conn.execute(delete(table).where(uid == unit, cond)).rowcount
                if n and on_deleted is not None:
                    on_deleted(conn, unit)
            result.batches += 1
            result.deleted[table.name] = result.deleted.get(table.name, 0) + max(n, 0)
            if edge is None:
                break
            if pause_s:
                time.sleep(pause_s)  # let the writer in between batches


def prune(
    engine: Engine,
    *,
    raw_days: float,
    rollup_days: float,
    now: float | None = None,
    batch_rows: int = 5000,
    pause_s: float = 0.0,
) -> PruneResult:
    """Delete raw rows older than `raw_days`; rollups, closed episodes and finished webhook
    deliveries (the delivery log) older than `rollup_days`."""
    now = time.time() if now is None else now
    # SQLite: take the write lock at BEGIN, as the writer does (see eqgw.store.engine).
    engine = engine.execution_options(sqlite_begin="IMMEDIATE")
    raw_cutoff = now - raw_days * DAY_S
    rollup_cutoff = now - rollup_days * DAY_S
    with engine.connect() as conn:
        unit_ids = list(conn.execute(select(_units.c.id).order_by(_units.c.id)).scalars())
    result = PruneResult()
    for table in RAW_TABLES:
        # A block of the raw archive goes once its last possible frame is past the cutoff.
        cut = raw_cutoff - {"raw_blocks": BLOCK_S, **BLOCK_SPAN_S}.get(table.name, 0.0)
        _prune_table(engine, table, "ts", cut, unit_ids, batch_rows, result, pause_s)
    _prune_table(
        engine,
        _rollups,
        "bucket_ts",
        rollup_cutoff,
        unit_ids,
        batch_rows,
        result,
        pause_s,
        on_deleted=bump_rollup_generation,
    )
    with engine.begin() as conn:
        n = conn.execute(
            delete(_episodes).where(
                _episodes.c.state == "closed", _episodes.c.ended_at < rollup_cutoff
            )
        ).rowcount
        result.deleted[_episodes.name] = max(n, 0)
        result.batches += 1
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
