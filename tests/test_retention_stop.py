"""A gateway that stops while its retention prune runs ends the prune with it: a cancel does
not stop the prune's thread, so the stop tells it to end before its next transaction and
waits for it. Nothing of the prune runs on the engine once the gateway has disposed of it (a
connection it opened then would be left open in a pool nobody uses)."""

from __future__ import annotations

import asyncio
import threading
import time
from typing import Any

from sqlalchemy import event, text

from eqgw.store.engine import create_engine
from eqgw.store.migrate import upgrade_engine
from eqgw.store.retention import DAY_S
from eqgw.store.writes import Batch, load_unit_ids, write_batch
from tests.api_helpers import served, wait_for

OLD_ROWS = 5000  # 50 delete transactions of 100, with the gateway's 0.05 s between them


def _seed_old_rows(url: str, now: float) -> None:
    engine = create_engine(url)
    try:
        upgrade_engine(engine)
        b = Batch()
        unit = ("OLD/can0", 0x1E)
        b.vehicles["OLD"] = {"id": "OLD", "name": "Old", "depot": None}
        b.units[unit] = "OLD"
        b.measurements = [
            (unit, {"ts": now - 40 * DAY_S + i, "v12": 12.0, "v24": 24.0, "i12": 0.0, "i24": 0.0})
            for i in range(OLD_ROWS)
        ]
        with engine.begin() as conn:
            write_batch(conn, b, load_unit_ids(conn))
    finally:
        engine.dispose()


def _old_rows_left(url: str, now: float) -> int:
    engine = create_engine(url)
    try:
        with engine.connect() as conn:
            sql = text("SELECT count(*) FROM measurements WHERE ts < :cut")
            return int(conn.execute(sql, {"cut": now - 30 * DAY_S}).scalar_one())
    finally:
        engine.dispose()


async def test_a_gateway_stopping_mid_prune_leaves_nothing_of_it_running(db_url: str) -> None:
    now = time.time()
    _seed_old_rows(db_url, now)
    disposed = threading.Event()
    deletes: list[float] = []
    after_dispose: list[str] = []
    async with served(db_url, vehicles=1, config={"retention": {"batch_rows": 100}}) as s:
        engine = s.rt.engine

        @event.listens_for(engine, "engine_disposed")
        def _disposed(_e: Any) -> None:
            disposed.set()

        @event.listens_for(engine, "before_cursor_execute")
        def _look(_c: Any, _cur: Any, statement: str, *_: Any) -> None:
            if disposed.is_set():
                after_dispose.append(statement)
            elif statement.startswith("DELETE FROM") and "measurements" in statement:
                # measurements, or its default partition on PostgreSQL
                deletes.append(time.monotonic())

        async def pruning() -> bool:
            return len(deletes) >= 2

        await wait_for(pruning, what="the retention prune deleting old rows")
    assert disposed.is_set()
    # A prune thread left running would go on with a batch every 0.05 s or so.
    await asyncio.sleep(1.0)
    assert after_dispose == [], after_dispose[:5]
    assert 0 < _old_rows_left(db_url, now) < OLD_ROWS  # stopped part-way, as meant
