"""Time of the migration that makes rollups a row per bucket (0019_rollup_rows), and of its
downgrade, per million rows of the layout before (a row per metric and bucket), on SQLite and
PostgreSQL.

Usage: python -m bench.rollup_migration [--rows 1000000] [--engines sqlite,postgresql]
                                        [--pg URL]

A database at the revision before gets unit-days of rollups as the gateway wrote them: the
13 metrics of an 80-series unit, every width (1,440 + 96 + 24 + 1 buckets a day: 20,293 rows
a unit-day), as many unit-days as `--rows` needs, in the last 30 days (on PostgreSQL the
day's partitions made first, as the keeper does). `upgrade_engine` runs the migration, timed;
the downgrade back, timed; the rows (metric and bucket pairs) are counted after each.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

from alembic import command
from alembic.script import ScriptDirectory
from sqlalchemy import Engine, text

from bench.prune import METRICS, PG_DEFAULT, pg_schema
from eqgw.store import partitions as parts
from eqgw.store.engine import create_engine, db_deadline
from eqgw.store.migrate import alembic_config, upgrade_engine
from eqgw.store.models import rollup_columns
from eqgw.store.writes import BUCKETS_S

REVISION = "0019_rollup_rows"
DAY_S = 86400
PER_UNIT_DAY = len(METRICS) * sum(DAY_S // w for w in BUCKETS_S)


def populate(engine: Engine, rows: int, today: float) -> int:
    """Unit-days of rollups of the layout before, `rows` at least; the rows written."""
    days = -(-rows // PER_UNIT_DAY)
    units = max(1, -(-days // 30))
    with engine.begin() as conn:
        conn.execute(text("INSERT INTO vehicles (id, name) VALUES ('MIG', 'MIG')"))
        for i in range(units):
            conn.execute(
                text("INSERT INTO units (bus, sa, vehicle_id) VALUES (:b, 30, 'MIG')"),
                {"b": f"MIG/can{i}"},
            )
        uids = [int(u) for u in conn.execute(text("SELECT id FROM units ORDER BY id")).scalars()]
    unit_days = [(uids[d % units], today - (1 + d // units) * DAY_S) for d in range(days)]
    pg = engine.dialect.name == "postgresql"
    if pg:
        for series in [parts.rollup_series(w) for w in BUCKETS_S]:
            for day in sorted({d for _, d in unit_days}):
                with engine.begin() as conn:
                    lo = parts.span_start(day, series.span_s)
                    parts.make_partition(conn, series, lo, lo + series.span_s)
    for uid, day in unit_days:
        with engine.begin() as conn:
            if pg:
                for w in BUCKETS_S:
                    conn.execute(
                        text(
                            f"INSERT INTO rollups SELECT {uid}, m, {w}, {day} + k * {w}, "
                            "20 + k % 7, 256.1 + k, 12.7 - k % 3 * 0.001, 12.9 + k % 5 * 0.001 "
                            "FROM unnest(CAST(:metrics AS text[])) m, "
                            f"generate_series(0, {DAY_S // w - 1}) k"
                        ),
                        {"metrics": METRICS},
                    )
            else:
                raw = conn.connection.driver_connection
                assert raw is not None
                raw.executemany(
                    "INSERT INTO rollups VALUES (?, ?, ?, ?, ?, ?, ?, ?)",
                    [
                        (uid, m, w, day + k * w, 20 + k % 7, 256.1 + k, 12.7 - k % 3 * 0.001,
                         12.9 + k % 5 * 0.001)
                        for m in METRICS
                        for w in BUCKETS_S
                        for k in range(DAY_S // w)
                    ],
                )  # fmt: skip
    return days * PER_UNIT_DAY


def pairs(engine: Engine, wide: bool) -> int:
    """The (metric, bucket) pairs held: rows before, non-null counts after."""
    with db_deadline(None), engine.connect() as conn:
        if not wide:
            return int(conn.execute(text("SELECT count(*) FROM rollups")).scalar_one())
        total = " + ".join(f"count({rollup_columns(m)[0]})" for m in METRICS)
        return int(conn.execute(text(f"SELECT {total} FROM rollups")).scalar_one())


def run(url: str, rows: int) -> tuple[int, float, float, int]:
    """(rows, upgrade s, downgrade s, rows after the upgrade) on a fresh database at `url`."""
    before = str(ScriptDirectory.from_config(alembic_config()).get_revision(REVISION).down_revision)
    engine = create_engine(url)
    try:
        upgrade_engine(engine, before)
        today = time.time() // DAY_S * DAY_S
        with db_deadline(None):
            n = populate(engine, rows, today)
        assert pairs(engine, wide=False) == n
        t = time.perf_counter()
        upgrade_engine(engine, REVISION)
        up_s = time.perf_counter() - t
        assert pairs(engine, wide=True) == n, "rows differ after the upgrade"
        with engine.connect() as conn:
            wide_rows = int(conn.execute(text("SELECT count(*) FROM rollups")).scalar_one())
        t = time.perf_counter()
        with db_deadline(None):
            command.downgrade(alembic_config(url), before)
        down_s = time.perf_counter() - t
        assert pairs(engine, wide=False) == n, "rows differ after the downgrade"
    finally:
        engine.dispose()
    return n, up_s, down_s, wide_rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rows", type=int, default=1_000_000)
    ap.add_argument("--engines", default="sqlite,postgresql")
    ap.add_argument("--pg", default=PG_DEFAULT)
    args = ap.parse_args()
    for name in args.engines.split(","):
        if name == "postgresql":
            with pg_schema(args.pg) as url:
                n, up_s, down_s, wide = run(url, args.rows)
        else:
            with tempfile.TemporaryDirectory() as tmp:
                n, up_s, down_s, wide = run(f"sqlite:///{Path(tmp) / 'db.sqlite'}", args.rows)
        m = n / 1e6
        print(
            f"{name:10} {n:,} rows -> {wide:,} rows: up {up_s:.1f} s ({up_s / m:.1f} s per "
            f"million rows), down {down_s:.1f} s ({down_s / m:.1f} s per million rows)",
            flush=True,
        )


if __name__ == "__main__":
    main()
