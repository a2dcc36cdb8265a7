"""What the shared write rate limit costs: one check (a transaction) on SQLite and PostgreSQL.

Counts writes of a few keys against the limit in the database, as every write through the API
does (app/store/limit_queries.py), from one thread and from eight at once, and prints the
median and 99th percentile time of one check. PostgreSQL is the test server
(EQGW_TEST_PG, default postgresql+psycopg://postgres@127.0.0.1:5432/test), in a schema of its
own that is dropped afterwards.

    PYTHONPATH=. python bench/write_limit.py
"""

from __future__ import annotations

import os
import statistics
import tempfile
import threading
import time
import uuid
from pathlib import Path

from sqlalchemy import Engine, text

from eqgw.security.keys import create_key
from eqgw.security.limit_repository import charge_write
from eqgw.store.engine import create_engine
from eqgw.store.migrate import upgrade_engine

PG = os.environ.get("EQGW_TEST_PG", "postgresql+psycopg://postgres@127.0.0.1:5432/test")
CHECKS = 400


def _run(engine: Engine, label: str) -> None:
    upgrade_engine(engine)
    keys = [create_key(engine, f"bench {i}", "operator")[0] for i in range(8)]
    limiter = engine.execution_options(sqlite_begin="IMMEDIATE")

    def check(key_id: int, out: list[float], n: int) -> None:
        for _ in range(n):
            t = time.perf_counter()
            with limiter.begin() as conn:
                charge_write(conn, key_id, 1_000_000, 60.0)
            out.append(time.perf_counter() - t)

    for threads in (1, 8):
        times: list[float] = []
        workers = [
            threading.Thread(target=check, args=(keys[i], times, CHECKS // threads))
            for i in range(threads)
        ]
        for w in workers:
            w.start()
        for w in workers:
            w.join()
        times.sort()
        p99 = times[int(len(times) * 0.99) - 1]
        print(
            f"{label}, {threads} thread(s): {len(times)} checks, "
            f"median {statistics.median(times) * 1000:.2f} ms, p99 {p99 * 1000:.2f} ms"
        )


def main() -> None:
    with tempfile.TemporaryDirectory() as tmp:
        engine = create_engine(f"sqlite:///{Path(tmp) / 'eqgw.db'}")
        try:
            _run(engine, "SQLite")
        finally:
            engine.dispose()
    schema = f"bench_{uuid.uuid4().hex[:12]}"
    admin = create_engine(PG)
    with admin.begin() as conn:
        conn.execute(text(f'CREATE SCHEMA "{schema}"'))
    engine = create_engine(f"{PG}?options=-csearch_path%3D{schema}")
    try:
        _run(engine, "PostgreSQL")
    finally:
        engine.dispose()
        with admin.begin() as conn:
            conn.execute(text(f'DROP SCHEMA "{schema}" CASCADE'))
        admin.dispose()


if __name__ == "__main__":
    main()
