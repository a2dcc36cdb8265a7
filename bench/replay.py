"""Replay benchmark: bare python-can LogReader vs `eqgw replay` into SQLite and PostgreSQL.

Usage: python -m bench.replay [--copies 100] [--pg URL] [--keep]

Builds a large mixed log by tiling the realistic fixture (tests/fixtures/mixed_bus.log: two
vehicles, three equalizers, ordinary J1939 traffic, broken transfers) end to end in time, then
prints frames/s and records/s of each path, the ratios to the bare read, a live-ingest rate
into PostgreSQL (frames already in memory, as from a bus) and disk bytes per vehicle-day.
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
import uuid
from pathlib import Path
from typing import Any

import can
from sqlalchemy import text

from eqgw.config import Settings
from eqgw.ingest.pipeline import BusBinding, IngestPipeline
from eqgw.ingest.replay import replay_file
from eqgw.ingest.writer import BatchedWriter
from eqgw.store.engine import create_engine
from eqgw.store.migrate import upgrade_engine

ROOT = Path(__file__).resolve().parents[1]
FIXTURE = ROOT / "tests" / "fixtures" / "mixed_bus.log"
SPAN_S = 120.0  # the fixture covers two minutes
VEHICLES = 2
PG_DEFAULT = os.environ.get("EQGW_BENCH_PG", "postgresql+psycopg://postgres@127.0.0.1:5432/test")
BUSES: list[dict[str, Any]] = [
    {
        "name": "BUS-101/can0",
        "vehicle_id": "BUS-101",
        "interface": "virtual",
        "channel": "can0",
        "equalizer_sas": [30, 31],
    },
    {"name": "BUS-102/can1", "vehicle_id": "BUS-102", "interface": "virtual", "channel": "can1"},
]
VEHICLE_CFG = [{"id": "BUS-101"}, {"id": "BUS-102"}]
VMAP = ["can0=BUS-101", "can1=BUS-102"]


def build_log(path: Path, copies: int) -> int:
    """Tile the fixture `copies` times, each shifted by its span; returns the frame count."""
    frames = list(can.LogReader(str(FIXTURE)))
    n = 0
    with can.Logger(str(path)) as out:
        for k in range(copies):
            shift = k * SPAN_S
            for m in frames:
                out.on_message_received(
                    can.Message(
                        timestamp=round(m.timestamp + shift, 6),
                        arbitration_id=m.arbitration_id,
                        data=m.data,
                        is_extended_id=m.is_extended_id,
                        channel=m.channel,
                        dlc=m.dlc,
                    )
                )
                n += 1
    return n


def bare_read(path: Path) -> tuple[int, float]:
    t = time.perf_counter()
    n = sum(1 for _ in can.LogReader(str(path)))
    return n, time.perf_counter() - t


def pg_schema_url(admin_url: str) -> tuple[str, str]:
    schema = f"bench_{uuid.uuid4().hex[:8]}"
    eng = create_engine(admin_url)
    with eng.begin() as conn:
        conn.execute(text(f'CREATE SCHEMA "{schema}"'))
    eng.dispose()
    return f"{admin_url}?options=-csearch_path%3D{schema}", schema


def drop_schema(admin_url: str, schema: str) -> None:
    eng = create_engine(admin_url)
    with eng.begin() as conn:
        conn.execute(text(f'DROP SCHEMA "{schema}" CASCADE'))
    eng.dispose()


def sqlite_bytes(db: Path) -> int:
    eng = create_engine(f"sqlite:///{db}")
    with eng.connect() as conn:
        conn.exec_driver_sql("PRAGMA wal_checkpoint(TRUNCATE)")
    eng.dispose()
    return sum(p.stat().st_size for p in db.parent.glob(db.name + "*"))


def pg_bytes(url: str, schema: str) -> int:
    eng = create_engine(url, isolation_level="AUTOCOMMIT")  # VACUUM refuses transactions
    with eng.connect() as conn:
        conn.exec_driver_sql("VACUUM")
        n = conn.execute(
            text(
                "SELECT coalesce(sum(pg_total_relation_size(c.oid)), 0) FROM pg_class c "
                "JOIN pg_namespace n ON n.oid = c.relnamespace "
                "WHERE n.nspname = :s AND c.relkind = 'r'"
            ),
            {"s": schema},
        ).scalar_one()
    eng.dispose()
    return int(n)


def live_ingest(url: str, msgs: list[can.Message]) -> tuple[int, float]:
    """Frames already in memory through pipeline and writer into the database."""
    engine = create_engine(url)
    upgrade_engine(engine)
    settings = Settings(database_url=url, buses=BUSES, vehicles=VEHICLE_CFG)
    bindings = [BusBinding(b.name, b.vehicle_id, tuple(b.equalizer_sas)) for b in settings.buses]
    pipeline = IngestPipeline(
        bindings, channel_map={"can0": "BUS-101/can0", "can1": "BUS-102/can1"}
    )
    writer = BatchedWriter(engine, settings.writer)
    writer.start()
    t = time.perf_counter()
    # As the service does: frames come from the bus readers in batches of up to 1000.
    for i in range(0, len(msgs), 1000):
        pipeline.process_many(msgs[i : i + 1000])
        if pipeline.pending_rows >= 2048:
            writer.put(pipeline.take_rows())
    pipeline.finish()
    writer.put(pipeline.take_rows())
    writer.flush()
    dt = time.perf_counter() - t
    writer.stop()
    engine.dispose()
    return pipeline.stats.records, dt


def _report(name: str, s: Any, bare: float, goals: dict[str, float]) -> None:
    ratio = s.frames_per_s / bare
    ok = "ok" if ratio >= goals[name] else "BELOW GOAL"
    print(
        f"eqgw replay -> {name:<10}          {s.frames_per_s:>10,.0f} frames/s "
        f"{s.records_per_s:>9,.0f} records/s  ratio {ratio:.2f} (goal {goals[name]}: {ok})",
        flush=True,
    )


def _bare_rate(log: Path) -> float:
    n, dt = bare_read(log)
    print(f"python-can LogReader (bare read)   {n / dt:>10,.0f} frames/s", flush=True)
    return n / dt


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--copies", type=int, default=100, help="fixture copies (3893 frames each)")
    ap.add_argument("--pg", default=PG_DEFAULT, help="PostgreSQL URL ('' to skip)")
    ap.add_argument("--keep", action="store_true", help="keep the temporary files")
    args = ap.parse_args()

    tmp = Path(tempfile.mkdtemp(prefix="eqgw-bench-"))
    log = tmp / "mixed_big.log"
    frames = build_log(log, args.copies)
    vehicle_days = VEHICLES * args.copies * SPAN_S / 86400.0
    print(
        f"log: {log} ({frames:,} frames, {log.stat().st_size / 1e6:.1f} MB, "
        f"{args.copies * SPAN_S / 3600:.1f} h of {VEHICLES} vehicles)"
    )

    print("each replay's ratio is to a bare read of the same log just before it (a shared, noisy")
    print("machine: the bare rate itself moves by tens of percent from run to run)")

    settings = Settings(database_url="sqlite://", buses=BUSES, vehicles=VEHICLE_CFG)
    results: list[tuple[str, Any, int]] = []
    goals = {"sqlite": 0.5, "postgresql": 0.4}
    db = tmp / "bench.db"
    bare = _bare_rate(log)
    s = replay_file(log, VMAP, settings, database_url=f"sqlite:///{db}")
    results.append(("sqlite", s, sqlite_bytes(db)))
    _report("sqlite", s, bare, goals)
    if args.pg:
        url, schema = pg_schema_url(args.pg)
        try:
            bare = _bare_rate(log)
            s = replay_file(log, VMAP, settings, database_url=url)
            results.append(("postgresql", s, pg_bytes(url, schema)))
            _report("postgresql", s, bare, goals)
        finally:
            if not args.keep:
                drop_schema(args.pg, schema)
    for name, s, size in results:
        print(
            f"disk {name:<10} {size / vehicle_days / 1e6:>8.2f} MB per vehicle-day "
            f"({size / 1e6:.1f} MB for {vehicle_days:.3f} vehicle-days, "
            f"raw archive on, {sum(s.writer.inserted.values()):,} rows)"
        )
    if args.pg:
        msgs = list(can.LogReader(str(log)))
        url, schema = pg_schema_url(args.pg)
        try:
            recs, dt = live_ingest(url, msgs)
        finally:
            drop_schema(args.pg, schema)
        ok = "ok" if recs / dt >= 20_000 else "BELOW GOAL"
        print(
            f"live ingest -> postgresql (in-memory frames)  {len(msgs) / dt:>10,.0f} frames/s "
            f"{recs / dt:>9,.0f} records/s (goal 20,000: {ok})"
        )
    if not args.keep:
        for p in tmp.iterdir():
            p.unlink()
        tmp.rmdir()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
