"""Time of the migration that packs measurements and battery states into hourly blocks
(0017_packed_series), and of its downgrade, per million rows, on SQLite and PostgreSQL.

Usage: python -m bench.packed_migration [--rows 1000000] [--engines sqlite,postgresql]
                                        [--pg URL]

A database at the revision before gets `--rows` rows, 5/8 measurements (every 3 s) and 3/8
battery states (every 5 s, indexes 1-5), as many units as needed for a day each, days that
ended before the clock (all of it due for packing). `upgrade_engine` runs the migration,
timed; the downgrade back, timed; the rows are counted after each.
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path
from typing import Any

from alembic import command
from alembic.script import ScriptDirectory
from sqlalchemy import Engine, text

from bench.archive_size import PG_DEFAULT, database
from eqgw.store import packed, queries
from eqgw.store.engine import create_engine
from eqgw.store.migrate import alembic_config, upgrade_engine

REVISION = "0017_packed_series"
DAY_S = 86400


def _day(uid: int, start: float) -> tuple[list[tuple[Any, ...]], list[tuple[Any, ...]]]:
    m = [
        (
            uid,
            start + 3 * i,
            round((2700 + i % 13) * 0.005, 3),
            round((5500 + i % 17) * 0.005, 3),
            round((32000 + i % 41) * 0.05 - 1600.0, 2),
            round((32000 - i % 29) * 0.05 - 1600.0, 2),
        )
        for i in range(DAY_S // 3)
    ]
    b = []
    for i in range(DAY_S // 5):
        idx = 1 + i % 5
        bat = {1: "12v", 2: "12v", 3: "24v", 4: "24v"}.get(idx)
        soc = round(i % 1000 * 0.1, 1) if idx in (2, 4) else None
        soh = 99.5 if idx in (1, 3) else None
        small = 1 if idx == 5 else None
        temp = round(30250 * 0.1 - 3000.0, 1) if idx == 5 else None
        raw_t = 30250 if idx == 5 else None
        b.append(
            (uid, start + 5 * i, idx, bat, soc, soh, soh, soc, soh, soc, small, small, small,
             small, temp, raw_t)
        )  # fmt: skip
    return m, b


def populate(engine: Engine, rows: int) -> int:
    """`rows` rows of measurements and battery states, a unit per simulated day."""
    per_day = DAY_S // 3 + DAY_S // 5
    units = -(-rows // per_day)
    start = (time.time() // 3600) * 3600 - 3 * DAY_S
    with engine.begin() as conn:
        conn.execute(text("INSERT INTO vehicles (id, name) VALUES ('MIG', 'MIG')"))
        for i in range(units):
            conn.execute(
                text(
                    "INSERT INTO units (bus, sa, vehicle_id, last_seen) VALUES (:b, 30, 'MIG', :t)"
                ),
                {"b": f"MIG/can{i}", "t": start + DAY_S},
            )
        uids = [int(u) for u in conn.execute(text("SELECT id FROM units ORDER BY id")).scalars()]
    left = rows
    for uid in uids:
        m, b = _day(uid, start)
        m, b = m[: left * 5 // 8], b[: left - min(len(m), left * 5 // 8)]
        left -= len(m) + len(b)
        with engine.begin() as conn:
            raw = conn.connection.driver_connection
            assert raw is not None
            for table, data in (("measurements", m), ("battery_states", b)):
                if not data:
                    continue
                if engine.dialect.name == "postgresql":
                    with raw.cursor() as cur, cur.copy(f"COPY {table} FROM STDIN") as cp:
                        for row in data:
                            cp.write_row(row)
                else:
                    marks = ", ".join("?" * len(data[0]))
                    raw.executemany(f"INSERT INTO {table} VALUES ({marks})", data)
    return rows - left


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rows", type=int, default=1_000_000)
    ap.add_argument("--engines", default="sqlite,postgresql")
    ap.add_argument("--pg", default=os.environ.get("EQGW_BENCH_PG", PG_DEFAULT))
    args = ap.parse_args()
    script = ScriptDirectory.from_config(alembic_config())
    before = str(script.get_revision(REVISION).down_revision)
    for kind in args.engines.split(","):
        with tempfile.TemporaryDirectory() as tmp, database(kind, Path(tmp), args.pg) as url:
            engine = create_engine(url)
            try:
                upgrade_engine(engine, before)
                n = populate(engine, args.rows)
                t = time.perf_counter()
                upgrade_engine(engine, REVISION)
                up = time.perf_counter() - t
                with engine.connect() as conn:
                    counts = queries.row_counts(conn)
                    in_blocks = sum(packed.packed_counts(conn).values())
                got = counts["measurements"] + counts["battery_states"]
                t = time.perf_counter()
                command.downgrade(alembic_config(url), before)
                down = time.perf_counter() - t
                with engine.connect() as conn:
                    back = sum(
                        int(conn.execute(text(f"SELECT count(*) FROM {t}")).scalar_one())
                        for t in ("measurements", "battery_states")
                    )
            finally:
                engine.dispose()
            print(
                f"{kind:<10} {n:,} rows: up {up:.1f} s ({up / n * 1e6:.1f} s per million rows, "
                f"{in_blocks:,} into blocks), down {down:.1f} s ({down / n * 1e6:.1f} s per "
                f"million rows); load average {os.getloadavg()[0]:.0f} on {os.cpu_count()} cores"
            )
            assert got == n == back, (got, n, back)


if __name__ == "__main__":
    main()
