"""Dead tuples that packing leaves in a past day's partitions of measurements and battery
states on PostgreSQL, and what the partition keeper's round leaves after it truncates the
partitions packed whole.

Usage: python -m bench.packed_truncate [--units 4] [--pg URL]

A schema at the latest revision, the partitions of a day three days ago made; `--units`
simulated 80-series unit-days of that day (bench/packed_migration's day: measurements every
3 s, a battery-state record every 5 s, indexes 1-5 in turn) written, the units seen now,
every hour packed (`eqgw.store.packed.compact`, as the gateway's writer does); then one
round of the keeper (`eqgw.store.partitions.maintain`). After each, the day's partitions of
the two tables: bytes (table + indexes), live and dead tuples (pg_stat_user_tables, read
once the sessions that changed them ended).
"""

from __future__ import annotations

import argparse
import os
import time

from sqlalchemy import Engine, text

from bench.archive_size import PG_DEFAULT, pg_schema
from bench.packed_migration import populate
from eqgw.store import packed
from eqgw.store import partitions as parts
from eqgw.store.engine import create_engine, db_deadline
from eqgw.store.migrate import upgrade_engine
from eqgw.store.writes import BUCKETS_S

DAY_S = 86400
TABLES = ("measurements", "battery_states")


def day_partitions(engine: Engine, day: float) -> dict[str, tuple[int, int, int]]:
    """Per table, (bytes, live tuples, dead tuples) of its partition of `day`."""
    engine.dispose()  # the sessions end: their statistics are flushed
    time.sleep(1.0)
    out = {}
    with engine.connect() as conn:
        schema = parts.partition_schema(conn)
        for table in TABLES:
            (p,) = [x for x in parts.partitions(conn, table) if x.lo == day]
            row = conn.execute(
                text(
                    "SELECT pg_total_relation_size(c.oid), coalesce(s.n_live_tup, 0), "
                    "coalesce(s.n_dead_tup, 0) FROM pg_class c LEFT JOIN pg_stat_user_tables s "
                    "ON s.relid = c.oid WHERE c.oid = to_regclass(:t)"
                ),
                {"t": f'"{schema}"."{p.name}"'},
            ).one()
            out[table] = (int(row[0]), int(row[1]), int(row[2]))
    return out


def show(label: str, figures: dict[str, tuple[int, int, int]]) -> None:
    for table, (size, live, dead) in figures.items():
        print(f"  {label:<22} {table:<15} {size / 1e6:8.2f} MB  live {live:>9,}  dead {dead:>9,}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--units", type=int, default=4)
    ap.add_argument("--pg", default=os.environ.get("EQGW_BENCH_PG", PG_DEFAULT))
    args = ap.parse_args()
    now = time.time()
    with pg_schema(args.pg, "bench_truncate") as url:
        engine = create_engine(url)
        try:
            upgrade_engine(engine)
            # populate() writes whole days ending before the clock, 3 days ago at the hour.
            start = (now // 3600) * 3600 - 3 * DAY_S
            day = parts.span_start(start, DAY_S)
            for series in parts.all_series():
                with engine.begin() as conn:
                    lo = parts.span_start(start, series.span_s)
                    for k in range(3):
                        parts.make_partition(
                            conn, series, lo + k * series.span_s, lo + (k + 1) * series.span_s
                        )
            per_day = DAY_S // 3 + DAY_S // 5
            with db_deadline(None):
                rows = populate(engine, args.units * per_day)
                with engine.begin() as conn:
                    conn.execute(text("UPDATE units SET last_seen = :t"), {"t": now})
                t = time.perf_counter()
                n = packed.compact(engine, now=now)
                pack_s = time.perf_counter() - t
            print(
                f"{args.units} unit-days, {rows:,} rows, {n:,} packed in {pack_s:.1f} s "
                f"(the day's partitions from {time.strftime('%Y-%m-%d %H:%M', time.gmtime(day))})"
            )
            # populate() starts at an hour: its days straddle two day partitions.
            for d in (day, day + DAY_S):
                label = f"packed ({time.strftime('%m-%d', time.gmtime(d))})"
                show(label, day_partitions(engine, d))
            t = time.perf_counter()
            result = parts.maintain(
                engine, raw_days=30, rollup_days=dict.fromkeys(BUCKETS_S, 30.0), now=now
            )
            round_s = time.perf_counter() - t
            print(f"keeper's round {round_s:.2f} s: truncated {', '.join(result.truncated)}")
            for d in (day, day + DAY_S):
                show(
                    f"truncated ({time.strftime('%m-%d', time.gmtime(d))})",
                    day_partitions(engine, d),
                )
        finally:
            engine.dispose()


if __name__ == "__main__":
    main()
