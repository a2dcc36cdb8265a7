"""Time of the migration that packs `raw_frames` into `raw_blocks` (0012_rawblocks), per
million rows, on SQLite and PostgreSQL.

Usage: python -m bench.archive_migration [--rows 1000000] [--engines sqlite,postgresql]
                                         [--pg URL]

A database at the revision before 0012_rawblocks gets `--rows` raw_frames rows: a simulated
day of an 80-series vehicle (bench/raw_export.py), the same day for as many units as needed. Then
`upgrade_engine` runs the migration, timed; the frames in the archive are counted after it.
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path

from alembic.script import ScriptDirectory
from sqlalchemy import Engine, text

from bench.archive_size import PG_DEFAULT, database
from bench.raw_export import a_day
from eqgw.store import archive
from eqgw.store.archive import CAN_EFF_MASK, Frame
from eqgw.store.engine import create_engine
from eqgw.store.migrate import alembic_config, upgrade_engine

_SQLITE_INSERT = "INSERT INTO raw_frames (unit_id, ts, can_id, seq, data) VALUES (?, ?, ?, ?, ?)"


def populate(engine: Engine, day: list[Frame], rows: int) -> int:
    """`rows` raw_frames rows (as the revision before keeps them), a unit per simulated day."""
    units = -(-rows // len(day))
    with engine.begin() as conn:
        conn.execute(text("INSERT INTO vehicles (id, name) VALUES ('MIG', 'MIG')"))
        for i in range(units):
            conn.execute(
                text("INSERT INTO units (bus, sa, vehicle_id) VALUES (:b, 30, 'MIG')"),
                {"b": f"MIG/can{i}"},
            )
        uids = [int(u) for u in conn.execute(text("SELECT id FROM units ORDER BY id")).scalars()]
    left = rows
    for uid in uids:
        batch = [(uid, f.ts, f.word & CAN_EFF_MASK, f.seq, f.data) for f in day[:left]]
        left -= len(batch)
        if engine.dialect.name == "postgresql":
            with engine.begin() as conn:
                raw = conn.connection.driver_connection
                assert raw is not None
                with (
                    raw.cursor() as cur,
                    cur.copy("COPY raw_frames (unit_id, ts, can_id, seq, data) FROM STDIN") as cp,
                ):
                    for row in batch:
                        cp.write_row(row)
        else:
            with engine.begin() as conn:
                raw = conn.connection.driver_connection
                assert raw is not None
                raw.executemany(_SQLITE_INSERT, batch)
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rows", type=int, default=1_000_000)
    ap.add_argument("--engines", default="sqlite,postgresql")
    ap.add_argument("--pg", default=os.environ.get("EQGW_BENCH_PG", PG_DEFAULT))
    args = ap.parse_args()
    day = a_day()
    script = ScriptDirectory.from_config(alembic_config())
    before = str(script.get_revision("0012_rawblocks").down_revision)
    for kind in args.engines.split(","):
        with tempfile.TemporaryDirectory() as tmp, database(kind, Path(tmp), args.pg) as url:
            engine = create_engine(url)
            try:
                upgrade_engine(engine, before)
                n = populate(engine, day, args.rows)
                t = time.perf_counter()
                upgrade_engine(engine, "0012_rawblocks")
                seconds = time.perf_counter() - t
                with engine.connect() as conn:
                    got = archive.count_frames(conn)
                    blocks = int(conn.execute(text("SELECT count(*) FROM raw_blocks")).scalar_one())
            finally:
                engine.dispose()
            print(
                f"{kind:<10} {n:,} raw_frames rows -> {blocks:,} blocks holding {got:,} frames "
                f"in {seconds:.1f} s: {seconds / n * 1e6:.1f} s per million rows"
            )
            assert got == n, (got, n)


if __name__ == "__main__":
    main()
