"""CSV export benchmark: the memory a streamed export of a big range holds, against reading the
range at once.

Usage: python -m bench.exports [--url URL] [--rows 200000]

Seeds `--rows` audit entries (spread over 30 days, over 50 vehicles) into a fresh SQLite file,
or into URL (a PostgreSQL database the bench may write to, emptied of audit entries first),
then, in this process:
- streams the whole range as the API does (`csv_export.csv_pages`, a page a transaction in a
  worker thread), counting rows and bytes, and reports tracemalloc's peak during the stream;
- reads the same range at once (`list_audit` with a limit of every row, then CSV), the peak of
  which is what an export without pages would hold.
"""

from __future__ import annotations

import argparse
import asyncio
import tempfile
import time
import tracemalloc
from collections.abc import Callable
from pathlib import Path
from typing import Any

from sqlalchemy import delete, insert

from eqgw.security import repository as api_queries
from eqgw.security.endpoints import AUDIT_COLUMNS
from eqgw.store.api_models import AuditEntry
from eqgw.store.engine import create_engine
from eqgw.store.migrate import upgrade_engine
from eqgw.web import csv_export


class _Db:
    """What `csv_pages` needs of the API's Runtime: a query in a worker thread, a transaction."""

    def __init__(self, engine: Any) -> None:
        self.engine = engine

    async def db(self, fn: Callable[..., Any], *args: Any) -> Any:
        def run() -> Any:
            with self.engine.begin() as conn:
                return fn(conn, *args)

        return await asyncio.to_thread(run)


def seed(engine: Any, rows: int) -> None:
    table = AuditEntry.__table__
    t0 = time.time() - 30 * 86400
    with engine.begin() as conn:
        conn.execute(delete(table))
        batch = []
        for i in range(rows):
            batch.append(
                {
                    "ts": t0 + i * (30 * 86400 / rows),
                    "key_id": 1,
                    "key_name": "bench key",
                    "role": "operator",
                    "action": "command.control",
                    "vehicle_id": f"BENCH-{i % 50:03d}",
                    "target": "unit 30",
                    "request": {"all_units": True, "jump_start_override": True},
                    "outcome": "accepted",
                    "status_code": 202,
                    "detail": None,
                    "command_id": None,
                }
            )
            if len(batch) == 5000:
                conn.execute(insert(table), batch)
                batch = []
        if batch:
            conn.execute(insert(table), batch)


def _page(conn: Any, after: int, limit: int) -> list[dict[str, Any]]:
    return api_queries.list_audit(conn, after_id=after, limit=limit)


async def _stream(db: _Db) -> tuple[int, int]:
    rows = size = 0
    async for chunk in csv_export.csv_pages(db, AUDIT_COLUMNS, _page):  # type: ignore[arg-type]
        rows += chunk.count(b"\n")
        size += len(chunk)
    return rows - 1, size


def run(url: str, rows: int) -> None:
    engine = create_engine(url)
    upgrade_engine(engine)
    try:
        t = time.perf_counter()
        seed(engine, rows)
        print(
            f"seeded {rows} audit entries in {time.perf_counter() - t:.1f} s ({url.split(':')[0]})"
        )
        db = _Db(engine)

        t = time.perf_counter()
        sent, size = asyncio.run(_stream(db))
        took = time.perf_counter() - t
        print(f"streamed: {sent} rows, {size / 1e6:.1f} MB of CSV in {took:.1f} s "
              f"({sent / took:,.0f} rows/s), page {csv_export.PAGE}")  # fmt: skip

        tracemalloc.start()
        t = time.perf_counter()
        sent, size = asyncio.run(_stream(db))
        took = time.perf_counter() - t
        _, peak = tracemalloc.get_traced_memory()
        tracemalloc.stop()
        print(f"streamed again under tracemalloc: {sent} rows, peak {peak / 1e6:.1f} MB")

        tracemalloc.start()
        with engine.begin() as conn:
            everything = api_queries.list_audit(conn, limit=rows + 1)
        body = csv_export._rows_csv(everything, AUDIT_COLUMNS)
        _, peak = tracemalloc.get_traced_memory()
        tracemalloc.stop()
        print(
            f"at once:  {len(everything)} rows, {len(body) / 1e6:.1f} MB: peak {peak / 1e6:.1f} MB"
        )
    finally:
        engine.dispose()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--url", help="a PostgreSQL URL (default: a fresh SQLite file)")
    ap.add_argument("--rows", type=int, default=200_000)
    args = ap.parse_args()
    if args.url:
        run(args.url, args.rows)
        return
    with tempfile.TemporaryDirectory() as tmp:
        run(f"sqlite:///{Path(tmp) / 'bench.db'}", args.rows)


if __name__ == "__main__":
    main()
