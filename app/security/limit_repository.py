"""Queries of the write rate limit shared by every gateway of a database; each takes a sync
Connection (the caller's transaction)."""

from __future__ import annotations

import time
from typing import Any

from sqlalchemy import (
    ColumnElement,
    Connection,
    Double,
    cast,
    delete,
    func,
    insert,
    literal,
    select,
)
from sqlalchemy.dialects import postgresql, sqlite

from eqgw.store.models import table_of
from eqgw.store.security_models import WriteBudget, WriteHit

_budgets = table_of(WriteBudget)
_hits = table_of(WriteHit)


def charge_write(conn: Connection, key_id: int, limit: int, window_s: float) -> float | None:
    """Count a write of `key_id` if fewer than `limit` were counted in the last `window_s`
    seconds (a sliding window); None when counted, else the seconds until one will be.

    The key's row in `write_budgets` is upserted first: on PostgreSQL the upsert locks it until
    the transaction ends, on SQLite the transaction holds the database's write lock, so one
    key's checks, from any process, run one after the other. The time is the database
    server's on PostgreSQL (gateways on several hosts share one clock), this host's on SQLite.
    """
    now_expr: ColumnElement[Any]
    if conn.dialect.name == "postgresql":
        now_expr = cast(func.extract("epoch", func.clock_timestamp()), Double)
        pg = postgresql.insert(_budgets).values(key_id=key_id, checked_at=now_expr)
        stmt: Any = pg.on_conflict_do_update(
            index_elements=[_budgets.c.key_id], set_={"checked_at": pg.excluded.checked_at}
        )
    else:
        now_expr = literal(time.time(), Double)
        lite = sqlite.insert(_budgets).values(key_id=key_id, checked_at=now_expr)
        stmt = lite.on_conflict_do_update(
            index_elements=[_budgets.c.key_id], set_={"checked_at": lite.excluded.checked_at}
        )
    now = float(conn.execute(stmt.returning(_budgets.c.checked_at)).scalar_one())
    since = now - window_s
    conn.execute(delete(_hits).where(_hits.c.key_id == key_id, _hits.c.ts <= since))
    count, oldest = conn.execute(
        select(func.count(), func.min(_hits.c.ts)).where(_hits.c.key_id == key_id)
    ).one()
    if count >= limit:
        if count > limit:  # the limit was lowered since: the write that frees a place
            oldest = conn.execute(
                select(_hits.c.ts)
                .where(_hits.c.key_id == key_id)
                .order_by(_hits.c.ts)
                .offset(count - limit)
                .limit(1)
            ).scalar_one()
        return max(0.0, float(oldest) + window_s - now)
    conn.execute(insert(_hits).values(key_id=key_id, ts=now))
    return None


def prune_write_hits(conn: Connection, window_s: float) -> int:
    """Delete the counted writes older than a window (of keys that stopped writing: a key's
    own are dropped at its next check); the number deleted."""
    return int(conn.execute(delete(_hits).where(_hits.c.ts <= time.time() - window_s)).rowcount)
