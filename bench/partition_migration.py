"""Time of the migration that partitions the time-series tables (0018_partitions), up and down,
per million rows, on PostgreSQL.

Usage: python -m bench.partition_migration [--vehicles 8] [--pg URL]

A schema at the revision before 0018_partitions gets fleet-days of rows (bench/prune.py's
unit-day: measurements, battery states, raw blocks, rollups of every width, changes), spread
over two days; `upgrade_engine` runs the migration, timed, then the downgrade, timed; the
rows are counted before and after each.
"""

from __future__ import annotations

import argparse
import time

from alembic import command
from alembic.script import ScriptDirectory
from sqlalchemy import Engine, text

from bench.prune import DAY_S, PG_DEFAULT, pg_schema, populate_pg
from eqgw.store.engine import create_engine, db_deadline
from eqgw.store.migrate import alembic_config, upgrade_engine

REVISION = "0018_partitions"
TABLES = (
    "measurements", "battery_states", "status_changes", "dm1_snapshots", "messages",
    "raw_blocks", "raw_recent", "rollups",
)  # fmt: skip


def counts(engine: Engine) -> dict[str, int]:
    with db_deadline(None), engine.connect() as conn:
        return {
            t: int(conn.execute(text(f"SELECT count(*) FROM {t}")).scalar_one()) for t in TABLES
        }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--vehicles", type=int, default=8)
    ap.add_argument("--pg", default=PG_DEFAULT)
    args = ap.parse_args()
    before = str(ScriptDirectory.from_config(alembic_config()).get_revision(REVISION).down_revision)
    with pg_schema(args.pg) as url:
        engine = create_engine(url)
        try:
            upgrade_engine(engine, before)
            day = time.time() - 2 * DAY_S
            with db_deadline(None):
                populate_pg(engine, args.vehicles, day - day % DAY_S)
            n0 = counts(engine)
            rows = sum(n0.values())
            t = time.perf_counter()
            upgrade_engine(engine, REVISION)
            up_s = time.perf_counter() - t
            assert counts(engine) == n0, "rows differ after the upgrade"
            t = time.perf_counter()
            with db_deadline(None):
                command.downgrade(alembic_config(url), before)
            down_s = time.perf_counter() - t
            assert counts(engine) == n0, "rows differ after the downgrade"
        finally:
            engine.dispose()
    m = rows / 1e6
    print(f"{rows:,} rows ({n0})")
    print(f"upgrade to {REVISION}: {up_s:.2f} s ({up_s / m:.2f} s per million rows)")
    print(f"downgrade:              {down_s:.2f} s ({down_s / m:.2f} s per million rows)")


if __name__ == "__main__":
    main()
