"""Bytes per archived frame: a simulated fleet-hour replayed through the ingest (pipeline and
writer) into SQLite and PostgreSQL, its minutes packed; the raw archive's table, index and
TOAST bytes divided by the frames it holds, against the 16-byte floor of a frame packed
without compression (timestamp, identifier, data) and against the one-row-per-frame
`raw_frames` table it replaced (the same frames inserted into one).

Usage: python -m bench.archive_size [--vehicles 20] [--minutes 60] [--engines sqlite,postgresql]
                                    [--pg URL] [--fixture-copies N]

The simulator stamps the frames of one tick with one time; here each vehicle's frames of a
tick are spread 540 us apart (an 8-byte extended frame's time on a 250 kbit/s bus), on the
microsecond grid as SocketCAN stamps them, so the time column is not flattered. The bench
replays minutes that have ended: everything is packed, `raw_recent` is empty (live, it holds
the last two minutes or so). `--fixture-copies N` replays tests/fixtures/mixed_bus.log tiled N
times instead (its payloads vary more than the simulator's: a less flattering figure).
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import can
from sqlalchemy import Engine, text

from eqgw.config import Settings
from eqgw.ingest.replay import replay_file
from eqgw.sim.clock import ManualClock
from eqgw.sim.fleet import SimulatedFleet
from eqgw.store import archive
from eqgw.store.engine import create_engine

PG_DEFAULT = os.environ.get("EQGW_BENCH_PG", "postgresql+psycopg://postgres@127.0.0.1:5432/test")
FLOOR = 16.0
FRAMES_PER_UNIT_DAY = 172_800  # an 80-series unit, per the manuals' rates
FRAME_ON_WIRE_S = 0.00054


def simulate(vehicles: int, minutes: float) -> tuple[list[can.Message], list[str], list[int]]:
    """Every frame of a simulated fleet over `minutes` that ended ten minutes ago, each
    message's channel its vehicle; the vehicles; the equalizer addresses in use."""
    start = time.time() - minutes * 60 - 600
    fleet = SimulatedFleet(vehicles, seed=0, clock=ManualClock(start))
    sent: list[can.Message] = []
    for name, v in fleet.vehicles.items():

        def tap(m: can.Message, name: str = name) -> None:
            m.channel = name
            sent.append(m)

        v.taps.append(tap)
    with fleet:
        for _ in range(int(minutes * 6)):
            fleet.advance(10.0)
    # Frames of one vehicle and one tick, spread as a bus would send them.
    last: dict[str, tuple[float, int]] = {}
    for m in sent:
        tick, k = last.get(m.channel, (None, 0))
        k = k + 1 if tick == m.timestamp else 0
        last[m.channel] = (m.timestamp, k)
        m.timestamp = round(m.timestamp + k * FRAME_ON_WIRE_S, 6)
    sent.sort(key=lambda m: m.timestamp)
    sas = sorted({u.sa for v in fleet.vehicles.values() for u in v.spec.units})
    return sent, list(fleet.vehicles), sas


@contextmanager
def database(kind: str, workdir: Path, pg: str) -> Iterator[str]:
    if kind == "sqlite":
        yield f"sqlite:///{workdir / f'size-{uuid.uuid4().hex[:6]}.db'}"
        return
    with pg_schema(pg, "bench_archive") as url:
        yield url


@contextmanager
def pg_schema(pg: str, prefix: str) -> Iterator[str]:
    """A PostgreSQL schema of its own (and the one its time partitions go to), dropped after."""
    schema = f"{prefix}_{uuid.uuid4().hex[:8]}"
    admin = create_engine(pg)
    with admin.begin() as conn:
        conn.execute(text(f'CREATE SCHEMA "{schema}"'))
    try:
        yield f"{pg}?options=-csearch_path%3D{schema}"
    finally:
        with admin.begin() as conn:
            conn.execute(text(f'DROP SCHEMA "{schema}" CASCADE'))
            conn.execute(text(f'DROP SCHEMA IF EXISTS "{schema}_partitions" CASCADE'))
        admin.dispose()


def table_bytes(engine: Engine, table: str) -> int:
    """A table's bytes with its indexes (and TOAST on PostgreSQL), after a VACUUM."""
    if engine.dialect.name == "postgresql":
        with engine.connect().execution_options(isolation_level="AUTOCOMMIT") as conn:
            conn.exec_driver_sql(f"VACUUM ANALYZE {table}")
            return int(
                conn.execute(
                    text(
                        # a partitioned table's bytes are its partitions' (0 itself)
                        "SELECT COALESCE(SUM(pg_total_relation_size(relid)), 0)"
                        " FROM pg_partition_tree(CAST(:t AS regclass))"
                    ),
                    {"t": table},
                ).scalar_one()
            )
    with engine.connect() as conn:
        names = [
            n
            for (n,) in conn.execute(
                text("SELECT name FROM sqlite_master WHERE tbl_name = :t"), {"t": table}
            )
        ]
        total = 0
        for name in names:
            total += int(
                conn.execute(
                    text("SELECT coalesce(sum(pgsize), 0) FROM dbstat WHERE name = :n"), {"n": name}
                ).scalar_one()
            )
        return total


def one_row_per_frame(engine: Engine) -> int:
    """The archive's frames inserted into a table shaped as raw_frames was; its bytes."""
    with engine.begin() as conn:
        conn.exec_driver_sql(
            "CREATE TABLE raw_frames_before (unit_id INTEGER NOT NULL, ts FLOAT8 NOT NULL, "
            "can_id BIGINT NOT NULL, seq SMALLINT NOT NULL DEFAULT 0, data BYTEA NOT NULL, "
            "CONSTRAINT pk_raw_frames_before PRIMARY KEY (unit_id, ts, can_id, seq))"
            + (" WITHOUT ROWID" if engine.dialect.name == "sqlite" else "")
        )
        uids = [int(u) for u in conn.execute(text("SELECT id FROM units")).scalars()]
        rows = [
            {"u": u, "t": f.ts, "c": f.can_id, "s": f.seq, "d": f.data}
            for u, f in archive.read_frames(conn, uids)
        ]
        for i in range(0, len(rows), 20_000):
            conn.execute(
                text(
                    "INSERT INTO raw_frames_before (unit_id, ts, can_id, seq, data) "
                    "VALUES (:u, :t, :c, :s, :d)"
                ),
                rows[i : i + 20_000],
            )
    return table_bytes(engine, "raw_frames_before")


def measure(kind: str, msgs: list[can.Message], names: list[str], sas: list[int], pg: str) -> None:
    with tempfile.TemporaryDirectory() as tmp, database(kind, Path(tmp), pg) as url:
        vmap: dict[str | None, str] = {n: n for n in names}
        settings = Settings(database_url=url)
        if not names:  # the fixture log: its two buses as bench.replay configures them
            from bench.replay import BUSES, VEHICLE_CFG, VMAP

            vmap = {}
            for pair in VMAP:
                channel, vehicle = pair.split("=")
                vmap[channel] = vehicle
            settings = Settings(database_url=url, buses=BUSES, vehicles=VEHICLE_CFG)
        t = time.perf_counter()
        summary = replay_file(
            Path(tmp) / "fleet.log", vmap, settings, messages=msgs, sas=sas or None
        )
        replay_s = time.perf_counter() - t
        engine = create_engine(url)
        try:
            with engine.connect() as conn:
                frames = archive.count_frames(conn)
                blocks = int(conn.execute(text("SELECT count(*) FROM raw_blocks")).scalar_one())
                waiting = int(conn.execute(text("SELECT count(*) FROM raw_recent")).scalar_one())
                units = int(conn.execute(text("SELECT count(*) FROM units")).scalar_one())
                data = int(
                    conn.execute(
                        text("SELECT coalesce(sum(length(data)), 0) FROM raw_blocks")
                    ).scalar_one()
                )
            packed = table_bytes(engine, "raw_blocks")
            before = one_row_per_frame(engine)
        finally:
            engine.dispose()
        per = packed / frames
        print(
            f"{kind:<10} {frames:>9,} frames of {units} units in {blocks:,} blocks "
            f"(replayed in {replay_s:.0f} s, {summary.frames:,} frames read, {waiting} waiting)"
        )
        parts = "table+index" if kind == "sqlite" else "table+index+TOAST"
        print(
            f"{'':<10} raw_blocks {per:6.2f} B/frame ({parts}; compressed data alone "
            f"{data / frames:.2f})  vs floor {FLOOR:.0f} B: "
            f"{per / FLOOR:.2f}x  vs one row per frame {before / frames:6.1f} B/frame "
            f"({before / packed:.0f}x more)"
        )
        print(
            f"{'':<10} per unit-day ({FRAMES_PER_UNIT_DAY:,} frames): "
            f"{per * FRAMES_PER_UNIT_DAY / 1e6:.2f} MB packed, "
            f"{before / frames * FRAMES_PER_UNIT_DAY / 1e6:.1f} MB one row per frame"
        )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--vehicles", type=int, default=20)
    ap.add_argument("--minutes", type=float, default=60.0)
    ap.add_argument("--engines", default="sqlite,postgresql")
    ap.add_argument("--pg", default=PG_DEFAULT)
    ap.add_argument(
        "--fixture-copies",
        type=int,
        default=0,
        help="replay the mixed fixture log tiled N times instead (varied payloads, 2 vehicles)",
    )
    args = ap.parse_args()
    t = time.perf_counter()
    if args.fixture_copies:
        from bench.replay import build_log

        log = Path(tempfile.mkdtemp()) / "tiled.log"
        build_log(log, args.fixture_copies)
        msgs, names, sas = list(can.LogReader(str(log))), [], []
        print(
            f"tests/fixtures/mixed_bus.log tiled {args.fixture_copies} times: {len(msgs):,} frames"
        )
    else:
        msgs, names, sas = simulate(args.vehicles, args.minutes)
        print(
            f"simulated {args.vehicles} vehicles for {args.minutes:.0f} min: {len(msgs):,} "
            f"frames in {time.perf_counter() - t:.0f} s"
        )
    for kind in args.engines.split(","):
        measure(kind.strip(), msgs, names, sas, args.pg)


if __name__ == "__main__":
    main()
