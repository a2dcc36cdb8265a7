"""Storage: bytes per frame per table, per vehicle-day and per year for a fleet, with the raw
archive on and off, on SQLite and PostgreSQL; and history read times over a year of one unit.

1. A simulated fleet (`--vehicles`, the simulator's mix: some have two units) over `--hours`
   that ended ten minutes ago, replayed through the ingest (decoder, pipeline, writer:
   bench.archive_size.simulate and replay_file) into a fresh database, then every hour
   that ended packed (live, the last hour or two of each unit stay rows: a constant, not a
   growth). Every history table's bytes (PostgreSQL: pg_total_relation_size, table +
   indexes + TOAST, after VACUUM FULL; SQLite: dbstat pages of the table and its indexes)
   are divided by the frames received. "Rows as written": every measurement and battery
   state also copied into a table of a row each, shaped as the ingest writes them (the
   layout without packing). The raw archive's tables are what the raw archive adds; with it
   off (`raw_archive = false`) the ingest writes every other table the same.
2. Per vehicle-day (a vehicle with one unit): the packed bytes per frame times the frames
   a simulated unit sends a day, and times the manuals' 172,800; the rollups scale by time
   instead (their rows follow the clock, not the frames). Per year for 500 vehicles under
   the default retention: 30 days of everything but rollups, plus each rollup width up to
   its own retention (1 min 30 days, 15 min a year, 1 h and 1 d five years: the second
   year adds the wider ones again), for vehicles sending all day, every day (a bus or
   coach runs fewer hours: an upper bound). Then the time to prune one fleet-day
   (bench/prune.py).
3. History reads on PostgreSQL: a year of one unit written through the store's write path
   (write_batch: rows, and rollups of every width), a voltages sample and the five battery
   states every `--year-step` s (1800), every minute over the last `--dense-days` (2), then
   packed. The buckets the reads touch are those of a real unit (every 1 min bucket of the
   last 24 h, every hour of 30 days, every day of the year); the tables hold fewer 1 min
   buckets than a year of a real unit (`--year-step 60 --dense-days 365` writes them all:
   3 M rows, most of an hour). Timed: the dashboard's reads (static/js/vehicle.js: every
   chart field, the bucket picked as the API's `auto` does): 24 h at 1 min, 30 days auto
   (1 h), 365 days auto (1 d), `--reads` times each, through queries.series_many without
   the history cache (what a miss costs).

Usage: python -m bench.storage [--vehicles 4] [--hours 3] [--engines sqlite,postgresql]
                               [--pg URL] [--year-step 1800] [--dense-days 2] [--reads 60]
                               [--no-year]
"""

from __future__ import annotations

import argparse
import math
import os
import statistics
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from sqlalchemy import Engine, MetaData, text

from bench.archive_size import PG_DEFAULT, database, simulate
from bench.prune import measure_prune
from eqgw.config import RetentionSettings, Settings
from eqgw.ingest.replay import replay_file
from eqgw.store import archive, packed, queries
from eqgw.store.engine import create_engine
from eqgw.store.migrate import upgrade_engine
from eqgw.store.writes import BUCKETS_S, Batch, load_unit_ids, write_batch

FLOOR = 16.0  # bytes of a frame packed without compression: timestamp, identifier, data
FRAMES_PER_UNIT_DAY = 172_800
DAY_S = 86400.0
FLEET = 500
_RETENTION = RetentionSettings()  # the defaults
RAW_DAYS = _RETENTION.raw_days
# Each rollup width's retention, and its share of a day's rollup rows (buckets a day).
ROLLUP_DAYS_BY_WIDTH = _RETENTION.rollup_days_by_width()
_BUCKETS_A_DAY = {w: DAY_S / w for w in BUCKETS_S}
ROLLUP_SHARE = {w: n / sum(_BUCKETS_A_DAY.values()) for w, n in _BUCKETS_A_DAY.items()}
# Days of a day's rollups a fleet holds after a year: each width up to its retention.
ROLLUP_YEAR_DAYS = sum(
    ROLLUP_SHARE[w] * min(ROLLUP_DAYS_BY_WIDTH.get(w, _RETENTION.rollup_days), 365.0)
    for w in BUCKETS_S
)
RAW_TABLES = ("raw_blocks", "raw_recent")
# The history tables: what grows with frames and time (the others hold the fleet, keys,
# settings, a few rows each).
HISTORY = (
    "measurements",
    "measurement_blocks",
    "battery_states",
    "battery_blocks",
    "status_changes",
    "dm1_snapshots",
    "messages",
    "fault_episodes",
    "rollups",
    *RAW_TABLES,
)
BY_TIME = ("rollups",)  # tables whose rows follow the clock, not the frames
# The dashboard's chart fields (static/js/charts.js ALL_FIELDS).
CHART_FIELDS = ["v12", "v24", "i12", "i24", "soc_12v", "soc_24v", "soh_12v", "soh_24v"]


def table_sizes(engine: Engine) -> dict[str, int]:
    """Bytes of every table with rows, indexes included (and TOAST on PostgreSQL)."""
    out: dict[str, int] = {}
    if engine.dialect.name == "postgresql":
        with engine.connect().execution_options(isolation_level="AUTOCOMMIT") as conn:
            names = list(
                conn.execute(
                    text("SELECT tablename FROM pg_tables WHERE schemaname = current_schema()")
                ).scalars()
            )
            for name in names:
                if name.removesuffix(AS_ROWS) not in HISTORY:
                    continue
                # FULL: space freed by packing is given back (live, new rows reuse it).
                conn.exec_driver_sql(f'VACUUM FULL ANALYZE "{name}"')
                out[name] = int(
                    conn.execute(
                        text(
                            # a partitioned table's bytes are its partitions' (0 itself)
                            "SELECT COALESCE(SUM(pg_total_relation_size(relid)), 0)"
                            " FROM pg_partition_tree(CAST(:t AS regclass))"
                        ),
                        {"t": name},
                    ).scalar_one()
                )
        return out
    import sqlite3

    assert engine.url.database is not None
    db = sqlite3.connect(engine.url.database, isolation_level=None)
    db.execute("VACUUM")  # space freed by packing given back (live, new rows reuse it)
    db.close()
    with engine.connect() as conn:
        for table, index in conn.execute(text("SELECT tbl_name, name FROM sqlite_master")):
            if table.removesuffix(AS_ROWS) not in HISTORY:
                continue
            n = conn.execute(
                text("SELECT coalesce(sum(pgsize), 0) FROM dbstat WHERE name = :n"), {"n": index}
            ).scalar_one()
            out[table] = out.get(table, 0) + int(n)
    return out


AS_ROWS = "_as_rows"


def _pack_raw(engine: Engine) -> None:
    """The raw archive packed as a gateway keeps it. (On PostgreSQL, packing skips its turn
    while another process packs: the replay's writer may still be at it, on a busy machine.)"""
    for _ in range(120):
        archive.compact(engine)
        if not _rows(engine, "raw_recent"):
            return
        time.sleep(1.0)


def as_rows(engine: Engine) -> None:
    """Every measurement and battery state, packed or not, also in a table of a row each
    shaped as the ingest writes them (`<table>_as_rows`): the layout without packing."""
    md = MetaData()
    with engine.begin() as conn:
        for s in packed.SERIES:
            copy = s.rows.to_metadata(md, name=s.name + AS_ROWS)
            if engine.dialect.name == "postgresql":  # constraint names are per schema there
                conn.exec_driver_sql(f"CREATE TABLE {copy.name} (LIKE {s.name} INCLUDING ALL)")
            else:
                copy.create(conn)
            uids = [int(u) for u in conn.execute(text("SELECT id FROM units")).scalars()]
            rows = [(uid, *r) for uid in uids for r in packed.read_rows(conn, s, uid, -1e18, 1e18)]
            rows += [tuple(r) for r in conn.execute(text(f"SELECT * FROM {s.name}"))]
            rows.sort(key=lambda r: (r[0], s.key_of(r[1:])))
            cols = ["unit_id", *s.columns]
            for i in range(0, len(rows), 20_000):
                conn.execute(
                    copy.insert(), [dict(zip(cols, r, strict=True)) for r in rows[i : i + 20_000]]
                )


def _rows(engine: Engine, table: str) -> int:
    with engine.connect() as conn:
        return int(conn.execute(text(f"SELECT count(*) FROM {table}")).scalar_one())


@dataclass
class Fleet:
    """One engine's replay: bytes per table before and after packing."""

    kind: str
    frames: int
    units: int
    hours: float
    before: dict[str, int]
    after: dict[str, int]
    rows: dict[str, int] = field(default_factory=dict)  # logical rows per packed table
    packed_rows: dict[str, int] = field(default_factory=dict)  # of which in blocks


def replay_fleet(kind: str, vehicles: int, hours: float, pg: str, msgs: Any) -> Fleet:
    sent, names, sas = msgs
    with tempfile.TemporaryDirectory() as tmp, database(kind, Path(tmp), pg) as url:
        summary = replay_file(
            Path(tmp) / "fleet.log",
            {n: n for n in names},
            Settings(database_url=url),
            messages=sent,
            sas=sas,
        )
        engine = create_engine(url)
        try:
            units = _rows(engine, "units")
            _pack_raw(engine)
            # Every hour that ended packed (live, the last hour or two stay rows).
            packed.compact(engine, after_s=0.0)
            as_rows(engine)
            sizes = table_sizes(engine)
            before = {n: v for n, v in sizes.items() if not n.endswith(AS_ROWS)}
            before.update(
                {s.name: sizes[s.name + AS_ROWS] for s in packed.SERIES}
                | {s.blocks.name: 0 for s in packed.SERIES}
            )
            after = {n: v for n, v in sizes.items() if not n.endswith(AS_ROWS)}
            with engine.connect() as conn:
                counts = queries.row_counts(conn)
                in_blocks = packed.packed_counts(conn)
        finally:
            engine.dispose()
    return Fleet(
        kind,
        summary.frames,
        units,
        hours,
        before,
        after,
        {s.name: counts[s.name] for s in packed.SERIES},
        in_blocks,
    )


def per_frame_packed(f: Fleet) -> dict[str, float]:
    """Bytes per frame received, per table, in the steady state: measurements and battery
    states at the cost of a packed row (their blocks' bytes over the rows they hold)."""
    out: dict[str, float] = {}
    for name, size in f.after.items():
        if name in {s.name for s in packed.SERIES} or name in {
            s.blocks.name for s in packed.SERIES
        }:
            continue
        out[name] = size / f.frames
    for s in packed.SERIES:
        held = f.packed_rows[s.name]
        per_row = f.after.get(s.blocks.name, 0) / held if held else math.nan
        out[s.blocks.name] = per_row * f.rows[s.name] / f.frames
    return out


def per_vehicle_day(
    f: Fleet, per_frame: dict[str, float], raw: bool, *, manual_rate: bool = False
) -> float:
    """Bytes one unit adds a day, sending all day: at the simulator's frame rate, or (with
    `manual_rate`) at the manuals' 172,800 frames a day (the rollups follow the clock)."""
    sim_day = f.frames / f.units / (f.hours * 3600) * DAY_S
    total = 0.0
    for name, b in per_frame.items():
        if name in RAW_TABLES and not raw:
            continue
        if name in BY_TIME or not manual_rate:
            total += b * sim_day
        else:
            total += b * FRAMES_PER_UNIT_DAY
    return total


def print_fleet(f: Fleet) -> None:
    print(
        f"\n{f.kind}: {f.frames:,} frames of {f.units} units over {f.hours:g} h "
        f"({f.frames / f.units / f.hours / 3600:.2f} frames/s a unit; the manuals' 2.00)"
    )
    steady = per_frame_packed(f)
    names = sorted(
        {**f.before, **f.after},
        key=lambda n: -max(f.before.get(n, 0), f.after.get(n, 0)),
    )
    print(f"  {'table':<22}{'rows as written':>17}{'packed':>12}   (bytes per frame received)")
    for n in names:
        b = f.before.get(n, 0) / f.frames
        a = steady.get(n)
        a_txt = f"{a:12.2f}" if a is not None else f"{'-> blocks':>12}"
        print(f"  {n:<22}{b:17.2f}{a_txt}")
    for raw in (True, False):
        total_b = sum(v / f.frames for n, v in f.before.items() if raw or n not in RAW_TABLES)
        total_a = sum(v for n, v in steady.items() if raw or n not in RAW_TABLES)
        label = "raw on " if raw else "raw off"
        print(
            f"  all tables, {label}: {total_b:6.2f} B/frame as written, {total_a:6.2f} packed "
            f"(floor {FLOOR:.0f} B: {total_a / FLOOR:.2f}x)   per vehicle-day: "
            f"{per_vehicle_day(f, steady, raw) / 1e6:.2f} MB packed "
            f"({per_vehicle_day(f, steady, raw, manual_rate=True) / 1e6:.2f} at 172,800 "
            "frames a day)"
        )


def fleet_year(f: Fleet, raw: bool) -> float:
    """Bytes `FLEET` vehicles hold after a year under the default retention."""
    steady = per_frame_packed(f)
    per_day = per_vehicle_day(f, {n: b for n, b in steady.items() if n not in BY_TIME}, raw)
    rollups_day = per_vehicle_day(f, {n: b for n, b in steady.items() if n in BY_TIME}, raw)
    return FLEET * (per_day * min(RAW_DAYS, 365) + rollups_day * ROLLUP_YEAR_DAYS)


def prune_time(url: str, vehicles: int) -> str:
    """The time to prune one fleet-day (bench/prune.py: `vehicles` of them, partition drop
    and the batched DELETE of the same rows; scaled to `FLEET` by rows)."""
    fig = measure_prune(vehicles=vehicles, pg=url)
    scaled = fig.at(FLEET)
    lines = [
        f"\npruning one day of {vehicles} vehicles ({fig.rows:,} rows; bench/prune.py):",
        f"  postgresql partition drop {fig.pg_drop_s:6.2f} s, dead tuples left "
        f"{fig.pg_drop_dead_tuples:,}",
    ]
    if fig.pg_delete_s is not None:
        lines.append(
            f"  postgresql batched DELETE {fig.pg_delete_s:6.2f} s, dead tuples left "
            f"{fig.pg_delete_dead_tuples:,} (at {FLEET} vehicles: "
            f"{scaled['pg_delete_s'] / 60:.1f} min)"
        )
    if fig.sqlite_delete_s is not None:
        lines.append(
            f"  sqlite batched DELETE     {fig.sqlite_delete_s:6.2f} s (at {FLEET} vehicles: "
            f"{scaled['sqlite_delete_s'] / 60:.1f} min)"
        )
    return "\n".join(lines)


# -- a year of one unit and the dashboard's reads ----------------------------------------


def year_times(now: float, step: float, dense_days: float) -> list[float]:
    """Sample times over the year before `now`: every `step` s, and every min(step, 60) s
    over the last `dense_days` (every 1 min bucket the 24 h read touches has its sample)."""
    start = math.floor((now - 365 * DAY_S) / 3600) * 3600
    dense_from = now - dense_days * DAY_S
    out: list[float] = []
    t = start
    while t < dense_from:
        out.append(t)
        t += step
    t = math.ceil(dense_from / 60) * 60
    while t < now:
        out.append(t)
        t += min(step, 60.0)
    return out


def write_year(url: str, step: float, dense_days: float, now: float) -> tuple[int, int, float]:
    """A year of one unit through write_batch (rows and rollups of every width), measurements
    and the five battery states at each of `year_times`; then packed as the gateway would.
    Returns (unit id, rows, seconds)."""
    engine = create_engine(url)
    upgrade_engine(engine)
    key = ("YEAR/can0", 30)
    times = year_times(now, step, dense_days)
    rows = 0
    began = time.perf_counter()
    try:
        for lo in range(0, len(times), 4000):
            b = Batch()
            b.vehicles["YEAR"] = {"id": "YEAR", "name": "YEAR", "depot": None}
            b.units[key] = "YEAR"
            for ts in times[lo : lo + 4000]:
                day = math.sin(2 * math.pi * ts / DAY_S)
                b.measurements.append(
                    (
                        key,
                        {
                            "ts": ts,
                            "v12": round(2700 * 0.005 + round(day * 40) * 0.005, 3),
                            "v24": round(5420 * 0.005 + round(day * 70) * 0.005, 3),
                            "i12": round((32000 + round(day * 90)) * 0.05 - 1600.0, 2),
                            "i24": round((32000 + round(day * 40)) * 0.05 - 1600.0, 2),
                        },
                    )
                )
                for idx in range(1, 6):
                    b.battery_states.append((key, _battery(ts + idx * 0.1, idx, day)))
            b.seen[key] = [b.measurements[0][1]["ts"], b.measurements[-1][1]["ts"] + 0.5]
            with engine.begin() as conn:
                write_batch(conn, b, load_unit_ids(conn))
            rows += len(b.measurements) + len(b.battery_states)
        packed.compact(engine, now=now)
        with engine.connect() as conn:
            uid = load_unit_ids(conn)[key]
    finally:
        engine.dispose()
    return uid, rows, time.perf_counter() - began


def _battery(ts: float, idx: int, day: float) -> dict[str, Any]:
    row: dict[str, Any] = dict.fromkeys(packed.BATTERY_STATES.columns, None)
    row.update(ts=ts, idx=idx, battery={1: "12v", 2: "12v", 3: "24v", 4: "24v"}.get(idx))
    if idx in (1, 3):
        row.update(soc_achievable=95.0, soh=round(97 + idx * 0.1, 1), runtime_min=600.0)
    elif idx in (2, 4):
        row.update(soc=round(80 + round(day * 100) * 0.1, 1), dod=12.5, runtime_temp_adj_min=580.5)
    else:
        row.update(major_12v=1, minor_12v=0, major_24v=1, minor_24v=0)
        row.update(temperature_c=round(30250 * 0.1 - 3000.0, 1), temperature_raw=30250)
    return row


def time_reads(url: str, uid: int, now: float, rounds: int) -> None:
    engine = create_engine(url)
    try:
        cases: list[tuple[str, float, str]] = [
            ("24 h at 1 min", DAY_S, "1m"),
            ("30 d auto", 30 * DAY_S, queries.pick_resolution(now - 30 * DAY_S, now)),
            ("365 d auto", 365 * DAY_S, queries.pick_resolution(now - 365 * DAY_S, now)),
        ]
        for name, span, bucket in cases:
            ms: list[float] = []
            points = 0
            for _ in range(rounds):
                with engine.begin() as conn:
                    t0 = time.perf_counter()
                    got = queries.series_many(conn, uid, CHART_FIELDS, now - span, now, bucket)
                    ms.append((time.perf_counter() - t0) * 1000)
                points = sum(len(p) for p in got.values())
            ms.sort()
            p99 = ms[min(len(ms) - 1, math.ceil(0.99 * len(ms)) - 1)]
            print(
                f"  {name:<14} ({bucket:>3}, {len(CHART_FIELDS)} fields, {points:,} points): "
                f"p50 {statistics.median(ms):6.1f} ms  p99 {p99:6.1f} ms   goal p99 < 100 ms"
            )
    finally:
        engine.dispose()


def _timed(what: str, fn: Callable[[], Any]) -> Any:
    t = time.perf_counter()
    out = fn()
    print(f"({what}: {time.perf_counter() - t:.0f} s)")
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--vehicles", type=int, default=4)
    ap.add_argument("--hours", type=float, default=3.0)
    ap.add_argument("--engines", default="sqlite,postgresql")
    ap.add_argument("--pg", default=PG_DEFAULT)
    ap.add_argument(
        "--year-step", type=float, default=1800.0, help="seconds between a year's samples"
    )
    ap.add_argument("--dense-days", type=float, default=2.0, help="last days sampled every minute")
    ap.add_argument("--reads", type=int, default=60, help="timed reads per case")
    ap.add_argument("--no-year", action="store_true", help="skip the year and its reads")
    ap.add_argument(
        "--prune-vehicles",
        type=int,
        default=10,
        help="vehicles of the fleet-day pruned (bench/prune.py; 0: skip)",
    )
    args = ap.parse_args()
    msgs = _timed(
        f"simulated {args.vehicles} vehicles for {args.hours:g} h",
        lambda: simulate(args.vehicles, args.hours * 60),
    )
    fleets = []
    for kind in args.engines.split(","):
        f = _timed(
            f"{kind}: replayed",
            lambda kind=kind: replay_fleet(kind.strip(), args.vehicles, args.hours, args.pg, msgs),
        )
        print_fleet(f)
        fleets.append(f)
    print(
        f"\n{FLEET} vehicles after a year, default retention (raw {RAW_DAYS:g} d, rollups "
        + ", ".join(f"{w:g} s {d:g} d" for w, d in ROLLUP_DAYS_BY_WIDTH.items())
        + "), one unit a vehicle sending all day:"
    )
    for f in fleets:
        on, off = fleet_year(f, True), fleet_year(f, False)
        steady = per_frame_packed(f)
        rollups = (
            FLEET * per_vehicle_day(f, {n: steady[n] for n in BY_TIME}, True) * ROLLUP_YEAR_DAYS
        )
        print(
            f"  {f.kind:<10} raw on {on / 1e9:6.1f} GB   raw off {off / 1e9:6.1f} GB   "
            f"(of which rollups {rollups / 1e9:.1f} GB)   goal <= 150 GB"
        )
    if args.prune_vehicles and "postgresql" in args.engines:
        print(prune_time(args.pg, args.prune_vehicles))
    if args.no_year or "postgresql" not in args.engines:
        return
    now = time.time()
    with tempfile.TemporaryDirectory() as tmp, database("postgresql", Path(tmp), args.pg) as url:
        uid, rows, seconds = write_year(url, args.year_step, args.dense_days, now)
        print(
            f"\npostgresql: a year of one unit (samples every {args.year_step:g} s, the last "
            f"{args.dense_days:g} days every minute): {rows:,} rows and their rollups written "
            f"in {seconds:.0f} s, packed; the dashboard's reads (load average "
            f"{os.getloadavg()[0]:.0f} on {os.cpu_count()} cores):"
        )
        time_reads(url, uid, now, args.reads)


if __name__ == "__main__":
    main()
