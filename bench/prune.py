"""Time to prune one fleet-day of history: PostgreSQL dropping the day's partitions against the
batched DELETE of the same rows (same run), the dead tuples each leaves, and SQLite's DELETE.

Usage: python -m bench.prune [--vehicles 10] [--pg URL] [--no-sqlite]

One unit per vehicle, an 80-series equalizer at the simulator's rates (172,800+ frames a day;
bench/raw_export.py's simulated day: voltages every 3 s, battery states five records every
5 s), so a unit-day is:

    measurements     28,800   (PGN 65494 every 3 s)
    battery_states   86,400   (PGN 65497, 5 records every 5 s)
    raw_blocks        1,440   (a packed minute each, 1.5 KB)
    rollups           1,561   (1,440 + 96 + 24 + 1 buckets, the 13 metrics in each row;
                               20,293 where a revision before 0019_rollup_rows keeps a row
                               per metric and bucket: the plain tables below)
    status_changes       48, dm1_snapshots 48 (on a change only)

The same rows go into three databases: a PostgreSQL schema at the latest revision (the day's
partitions made first, as the gateway does), a PostgreSQL schema at the revision before the
partitions (plain tables), and a SQLite file. Each prunes the day (every retention set so
that the day is past it). The DELETE rate is linear in rows, so its time at 500 vehicles is
the measured rows/s over 500 vehicles' rows; the drop's time barely depends on rows.
"""

from __future__ import annotations

import argparse
import os
import random
import tempfile
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import asdict, dataclass
from pathlib import Path

from alembic.script import ScriptDirectory
from sqlalchemy import Engine, inspect, text

from bench import archive_size
from eqgw.store import partitions as parts
from eqgw.store.engine import create_engine, db_deadline
from eqgw.store.migrate import alembic_config, upgrade_engine
from eqgw.store.models import rollup_columns
from eqgw.store.retention import prune
from eqgw.store.writes import BUCKETS_S

PG_DEFAULT = os.environ.get("EQGW_BENCH_PG", "postgresql+psycopg://postgres@127.0.0.1:5432/test")
DAY_S = 86400
# Rows of one unit-day (see the module's docstring).
MEASUREMENT_STEP_S = 3.0
BATTERY_STEP_S = 5.0
BATTERY_INDEXES = 5
CHANGES_PER_DAY = 48
BLOCK_BYTES = 1500
METRICS = [
    *("v12", "v24", "i12", "i24"),
    *(f"{m}_{b}" for m in ("soc", "soc_achievable", "soh", "dod") for b in ("12v", "24v")),
    "temperature_c",
]
FLEET = 500


def unit_day_rows(rollup_per_metric: bool = False) -> dict[str, int]:
    """Rows of a unit-day by table; `rollup_per_metric`: rollups a row per metric and bucket
    (the layout before 0019_rollup_rows)."""
    return {
        "measurements": int(DAY_S / MEASUREMENT_STEP_S),
        "battery_states": int(DAY_S / BATTERY_STEP_S) * BATTERY_INDEXES,
        "raw_blocks": DAY_S // 60,
        "rollups": (len(METRICS) if rollup_per_metric else 1) * sum(DAY_S // w for w in BUCKETS_S),
        "status_changes": CHANGES_PER_DAY,
        "dm1_snapshots": CHANGES_PER_DAY,
    }


@dataclass(slots=True)
class PruneFigures:
    """One bench run: rows of the day, seconds to prune it each way, dead tuples left."""

    vehicles: int
    rows: int
    pg_drop_s: float
    pg_drop_dead_tuples: int
    pg_delete_s: float | None
    pg_delete_dead_tuples: int | None
    sqlite_delete_s: float | None
    pg_delete_rows: int | None = None  # the plain tables' rollups are a row per metric

    @property
    def pg_delete_rows_per_s(self) -> float | None:
        if self.pg_delete_s is None:
            return None
        return (self.pg_delete_rows or self.rows) / self.pg_delete_s

    def at(self, vehicles: int) -> dict[str, float]:
        """The DELETE times scaled to `vehicles` (linear in rows)."""
        k = vehicles / self.vehicles
        out = {}
        if self.pg_delete_s is not None:
            out["pg_delete_s"] = self.pg_delete_s * k
        if self.sqlite_delete_s is not None:
            out["sqlite_delete_s"] = self.sqlite_delete_s * k
        return out

    def as_dict(self) -> dict[str, object]:
        d: dict[str, object] = asdict(self)
        rate = self.pg_delete_rows_per_s
        d["pg_delete_rows_per_s"] = None if rate is None else round(rate)
        d[f"at_{FLEET}_vehicles"] = {k: round(v, 1) for k, v in self.at(FLEET).items()}
        return d


@contextmanager
def pg_schema(pg: str) -> Iterator[str]:
    with archive_size.pg_schema(pg, "bench_prune") as url:
        yield url


def _units(engine: Engine, vehicles: int) -> None:
    with engine.begin() as conn:
        for i in range(1, vehicles + 1):
            conn.execute(text("INSERT INTO vehicles (id, name) VALUES (:v, :v)"), {"v": f"B{i}"})
            conn.execute(
                text("INSERT INTO units (id, bus, sa, vehicle_id) VALUES (:i, :b, 30, :v)"),
                {"i": i, "b": f"B{i}/can0", "v": f"B{i}"},
            )


def populate_pg(engine: Engine, vehicles: int, day: float) -> int:
    """The fleet-day's rows, written server-side (generate_series)."""
    _units(engine, vehicles)
    n = vehicles
    blob = random.Random(0).randbytes(BLOCK_BYTES)
    stmts = [
        f"INSERT INTO measurements SELECT u, {day} + k * {MEASUREMENT_STEP_S}, 12.8, 25.6, 1, 2 "
        f"FROM generate_series(1, {n}) u, "
        f"generate_series(0, {int(DAY_S / MEASUREMENT_STEP_S) - 1}) k",
        f"INSERT INTO battery_states (unit_id, ts, idx, battery, soc, soh) "
        f"SELECT u, {day} + k * {BATTERY_STEP_S}, i, '12v', 80, 95 FROM generate_series(1, {n}) u, "
        f"generate_series(0, {int(DAY_S / BATTERY_STEP_S) - 1}) k, "
        f"generate_series(1, {BATTERY_INDEXES}) i",
        f"INSERT INTO raw_blocks SELECT u, {day} + k * 60, 183, :blob "
        f"FROM generate_series(1, {n}) u, generate_series(0, {DAY_S // 60 - 1}) k",
        f"INSERT INTO status_changes SELECT u, {day} + k * 1800 + 7, '{{}}', '[]' "
        f"FROM generate_series(1, {n}) u, generate_series(0, {CHANGES_PER_DAY - 1}) k",
        f"INSERT INTO dm1_snapshots SELECT u, {day} + k * 1800 + 9, '{{}}', '[]' "
        f"FROM generate_series(1, {n}) u, generate_series(0, {CHANGES_PER_DAY - 1}) k",
    ]
    per_metric = rollup_per_metric(engine)
    if per_metric:
        stmts += [
            f"INSERT INTO rollups SELECT u, m, {w}, {day} + k * {w}, 20, 256, 12.7, 12.9 "
            f"FROM generate_series(1, {n}) u, unnest(CAST(:metrics AS text[])) m, "
            f"generate_series(0, {DAY_S // w - 1}) k"
            for w in BUCKETS_S
        ]
    else:
        cols, values = _rollup_columns()
        stmts += [
            f"INSERT INTO rollups (unit_id, bucket_s, bucket_ts, {cols}) "
            f"SELECT u, {w}, {day} + k * {w}, {values} FROM generate_series(1, {n}) u, "
            f"generate_series(0, {DAY_S // w - 1}) k"
            for w in BUCKETS_S
        ]
    with engine.begin() as conn:
        conn.execute(text("SET LOCAL statement_timeout = 0"))  # big inserts, not the gateway's
        for sql in stmts:
            params = {"blob": blob} if ":blob" in sql else {}
            if ":metrics" in sql:
                params["metrics"] = METRICS
            conn.execute(text(sql), params)
    with engine.connect() as conn:
        auto = conn.execution_options(isolation_level="AUTOCOMMIT")
        auto.execute(text("SET statement_timeout = 0"))
        auto.execute(text("VACUUM ANALYZE"))
    return sum(unit_day_rows(per_metric).values()) * vehicles


def rollup_per_metric(engine: Engine) -> bool:
    """Whether the database's rollups are a row per metric (before 0019_rollup_rows)."""
    with engine.connect() as conn:
        return any(c["name"] == "metric" for c in inspect(conn).get_columns("rollups"))


def _rollup_columns() -> tuple[str, str]:
    """The columns of METRICS in a row of `rollups`, and the bench's values for them."""
    cols = [c for m in METRICS for c in rollup_columns(m)]
    values = ["20", "256", "12.7", "12.9"] * len(METRICS)
    return ", ".join(cols), ", ".join(values)


def populate_sqlite(engine: Engine, vehicles: int, day: float) -> None:
    _units(engine, vehicles)
    blob = random.Random(0).randbytes(BLOCK_BYTES)
    raw = engine.raw_connection()
    try:
        cur = raw.cursor()
        for u in range(1, vehicles + 1):
            cur.executemany(
                "INSERT INTO measurements VALUES (?, ?, 12.8, 25.6, 1, 2)",
                ((u, day + k * MEASUREMENT_STEP_S) for k in range(int(DAY_S / MEASUREMENT_STEP_S))),
            )
            cur.executemany(
                "INSERT INTO battery_states (unit_id, ts, idx, battery, soc, soh) "
                "VALUES (?, ?, ?, '12v', 80, 95)",
                (
                    (u, day + k * BATTERY_STEP_S, i)
                    for k in range(int(DAY_S / BATTERY_STEP_S))
                    for i in range(1, BATTERY_INDEXES + 1)
                ),
            )
            cur.executemany(
                "INSERT INTO raw_blocks VALUES (?, ?, 183, ?)",
                ((u, day + k * 60, blob) for k in range(DAY_S // 60)),
            )
            for table, off in (("status_changes", 7), ("dm1_snapshots", 9)):
                cur.executemany(
                    f"INSERT INTO {table} VALUES (?, ?, '{{}}', '[]')",
                    ((u, day + k * 1800 + off) for k in range(CHANGES_PER_DAY)),
                )
            cols, values = _rollup_columns()
            cur.executemany(
                f"INSERT INTO rollups (unit_id, bucket_s, bucket_ts, {cols}) "
                f"VALUES (?, ?, ?, {values})",
                ((u, w, day + k * w) for w in BUCKETS_S for k in range(DAY_S // w)),
            )
        raw.commit()
    finally:
        raw.close()


def dead_tuples(url: str) -> int:
    """n_dead_tup of every table of the schema and its partitions (after the pruning
    sessions ended, so their counts are flushed)."""
    engine = create_engine(url)
    try:
        with engine.connect() as conn:
            schema = conn.execute(text("SELECT current_schema()")).scalar_one()
            return int(
                conn.execute(
                    text(
                        "SELECT coalesce(sum(n_dead_tup), 0) FROM pg_stat_user_tables "
                        "WHERE schemaname IN (:s, :p)"
                    ),
                    {"s": schema, "p": f"{schema}_partitions"},
                ).scalar_one()
            )
    finally:
        engine.dispose()


def _prune_day(engine: Engine, day: float) -> float:
    """Seconds to prune the day: every retention a day, at a time when every partition
    holding the day (a rollup width's spans are up to 52 weeks) has ended."""
    now = max(parts.span_start(day, s.span_s) + s.span_s for s in parts.all_series()) + DAY_S + 1
    began = time.perf_counter()
    prune(
        engine,
        raw_days=1,
        rollup_days=1,
        rollup_days_by_width=dict.fromkeys(BUCKETS_S, 1.0),
        now=now,
    )
    return time.perf_counter() - began


def _timed_pg(url: str, vehicles: int, day: float, partitioned: bool) -> tuple[float, int, int]:
    engine = create_engine(url)
    try:
        if partitioned:
            upgrade_engine(engine)
            # The day's partitions, made ahead as the gateway's keeper does.
            for series in parts.all_series():
                with engine.begin() as conn:
                    lo = parts.span_start(day, series.span_s)
                    parts.make_partition(conn, series, lo, lo + series.span_s)
        else:
            before = ScriptDirectory.from_config(alembic_config()).get_revision("0018_partitions")
            upgrade_engine(engine, str(before.down_revision))
        with db_deadline(None):  # the bench's big inserts (and a loaded machine)
            rows = populate_pg(engine, vehicles, day)
            seconds = _prune_day(engine, day)
    finally:
        engine.dispose()  # the sessions end: their statistics are flushed
    time.sleep(1.0)
    return seconds, dead_tuples(url), rows


def measure_prune(
    vehicles: int = 10,
    pg: str = PG_DEFAULT,
    sqlite: bool = True,
    workdir: Path | None = None,
    delete: bool = True,
) -> PruneFigures:
    """Prune one fleet-day of `vehicles` on PostgreSQL (partition drop, then batched DELETE of
    the same rows unless not `delete`) and on SQLite; the figures."""
    day = time.time() - 400 * DAY_S
    day -= day % DAY_S
    with pg_schema(pg) as url:
        drop_s, drop_dead, rows = _timed_pg(url, vehicles, day, partitioned=True)
    delete_s: float | None = None
    delete_dead: int | None = None
    delete_rows: int | None = None
    if delete:
        with pg_schema(pg) as url:
            delete_s, delete_dead, delete_rows = _timed_pg(url, vehicles, day, partitioned=False)
    sqlite_s: float | None = None
    if sqlite:
        with tempfile.TemporaryDirectory(dir=workdir) as tmp:
            engine = create_engine(f"sqlite:///{Path(tmp) / 'prune.db'}")
            try:
                upgrade_engine(engine)
                populate_sqlite(engine, vehicles, day)
                sqlite_s = _prune_day(engine, day)
            finally:
                engine.dispose()
    return PruneFigures(
        vehicles, rows, drop_s, drop_dead, delete_s, delete_dead, sqlite_s, delete_rows
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--vehicles", type=int, default=10)
    ap.add_argument("--pg", default=PG_DEFAULT)
    ap.add_argument("--no-sqlite", action="store_true")
    ap.add_argument("--drop-only", action="store_true", help="PostgreSQL's partition drop only")
    args = ap.parse_args()
    per_unit = unit_day_rows()
    print(f"rows per unit-day: {per_unit} = {sum(per_unit.values()):,}")
    f = measure_prune(
        args.vehicles, args.pg, sqlite=not (args.no_sqlite or args.drop_only),
        delete=not args.drop_only,
    )  # fmt: skip
    print(f"fleet-day of {f.vehicles} vehicles: {f.rows:,} rows")
    print(
        f"PostgreSQL, partitions dropped:  {f.pg_drop_s:8.2f} s, "
        f"dead tuples left {f.pg_drop_dead_tuples:,}"
    )
    if f.pg_delete_s is not None:
        print(
            f"PostgreSQL, batched DELETE:      {f.pg_delete_s:8.2f} s "
            f"({f.pg_delete_rows_per_s:,.0f} rows/s of {f.pg_delete_rows or f.rows:,}), "
            f"dead tuples left {f.pg_delete_dead_tuples:,}"
        )
    if f.sqlite_delete_s is not None:
        print(
            f"SQLite, batched DELETE:          {f.sqlite_delete_s:8.2f} s "
            f"({f.rows / f.sqlite_delete_s:,.0f} rows/s)"
        )
    scaled = f.at(FLEET)
    print(
        f"at {FLEET} vehicles ({sum(per_unit.values()) * FLEET:,} rows a day): DELETE "
        + ", ".join(f"{k} {v / 60:.1f} min" for k, v in scaled.items())
        + f"; the drop: {f.pg_drop_s:.2f} s here (its time is per partition, not per row)"
    )


if __name__ == "__main__":
    main()
