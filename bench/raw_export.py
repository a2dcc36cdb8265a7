"""Raw export of a month of one vehicle: peak memory (tracemalloc) against the export's size,
per format, through the page reads and log writers `GET /vehicles/{id}/raw` and `eqgw export`
use (eqgw.store.archive.read_page, eqgw.bus.export); Linux.

Usage: python -m bench.raw_export [--days 30] [--engine sqlite|postgresql] [--pg URL]
                                  [--formats candump,asc,blf,mf4] [--traced-days 1,3]

The archive is filled with a day of a simulated 80-series vehicle (about 3 frames/s: its own
and the requests and commands addressed to it) repeated over `--days`, packed straight into
blocks (the writer's path is measured by bench/archive_size.py). Each format is then exported
in full, its bytes counted and dropped, with the process's resident peak above its size at
the start; then exported again over the last `--traced-days` under tracemalloc (several times
slower), whose peak is what the export held at most (Python and numpy objects: a page of
frames, the writers' buffers). The peak does not grow with the range. BLF and MF4 are made in
a temporary file first (their headers are written last), which the disk holds meanwhile.
"""

from __future__ import annotations

import argparse
import gc
import math
import os
import tempfile
import time
import tracemalloc
from collections.abc import Iterator
from pathlib import Path

import can
from sqlalchemy import Engine, text

from bench.archive_size import PG_DEFAULT, database
from eqgw.bus.export import FORMATS, ChannelFrame, LogExport, export_chunks
from eqgw.sim.clock import ManualClock
from eqgw.sim.fleet import SimulatedFleet
from eqgw.store import archive
from eqgw.store.archive import Frame, block_start, pack_block, word_of
from eqgw.store.engine import create_engine
from eqgw.store.migrate import upgrade_engine

VEHICLE = "SIM-001"
_INSERT = text("INSERT INTO raw_blocks (unit_id, ts, frames, data) VALUES (:u, :t, :n, :d)")


def a_day() -> list[Frame]:
    """A day of SIM-001's equalizer frames (SA 30), on the microsecond grid."""
    fleet = SimulatedFleet(1, seed=0, clock=ManualClock(time.time() - 2 * 86400))
    out: list[Frame] = []
    seen: dict[tuple[float, int], int] = {}

    def tap(m: can.Message) -> None:
        ts = round(m.timestamp, 6)
        cid = m.arbitration_id
        if cid & 0xFF != 30 and (cid >> 8) & 0xFF != 30:
            return  # other nodes' frames: the archive does not keep them
        seq = seen[(ts, cid)] = seen.get((ts, cid), -1) + 1
        out.append(Frame(ts, word_of(cid), seq, bytes(m.data)))

    fleet.vehicle(VEHICLE).taps.append(tap)
    with fleet:
        for _ in range(8640):
            fleet.advance(10.0)
    return out


def fill(engine: Engine, days: float) -> tuple[int, float, float]:
    """`days` of the vehicle's frames packed into raw_blocks; (frames, first ts, end)."""
    day = a_day()
    base = day[0].ts
    start = block_start(time.time() - days * 86400 - 3600)
    with engine.begin() as conn:
        conn.execute(text("INSERT INTO vehicles (id, name) VALUES (:v, :v)"), {"v": VEHICLE})
        conn.execute(
            text("INSERT INTO units (bus, sa, vehicle_id) VALUES (:b, 30, :v)"),
            {"b": f"{VEHICLE}/can0", "v": VEHICLE},
        )
        uid = int(conn.execute(text("SELECT id FROM units")).scalar_one())
    frames = 0
    end = start + days * 86400.0
    rows: list[dict[str, object]] = []
    for d in range(math.ceil(days)):
        shift = start + d * 86400.0 - base
        minutes: dict[float, list[Frame]] = {}
        for f in day:
            ts = round(f.ts + shift, 6)
            if ts < min(start + (d + 1) * 86400.0, end):
                minutes.setdefault(block_start(ts), []).append(f._replace(ts=ts))
        for m, fs in minutes.items():
            rows.append({"u": uid, "t": m, "n": len(fs), "d": pack_block(fs)})
            frames += len(fs)
            if len(rows) >= 2000:
                with engine.begin() as conn:
                    conn.execute(_INSERT, rows)
                rows = []
    if rows:
        with engine.begin() as conn:
            conn.execute(_INSERT, rows)
    return frames, start, end


def _rss_kb(field: str) -> int:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1])
    return 0


def export(
    engine: Engine, fmt: str, start: float, end: float, *, traced: bool
) -> tuple[int, int, float, int]:
    """(frames, bytes, seconds, peak bytes) of one whole export: the peak traced by
    tracemalloc, or (`traced` False) the process's resident peak above its size at the start
    (Linux: VmHWM reset through /proc/self/clear_refs)."""
    with engine.connect() as conn:
        uids = [int(u) for u in conn.execute(text("SELECT id FROM units")).scalars()]

    def pages() -> Iterator[list[ChannelFrame]]:
        cursor: float | None = start
        while cursor is not None:
            with engine.connect() as conn:
                page, cursor = archive.read_page(conn, uids, cursor, end)
            yield [(0, f) for _, f in page]

    log = LogExport(fmt)
    gc.collect()
    if traced:
        tracemalloc.start()
    else:
        rss_before = _rss_kb("VmRSS")
        Path("/proc/self/clear_refs").write_text("5")  # VmHWM := VmRSS
    t = time.perf_counter()
    size = 0
    for chunk in export_chunks(pages(), log):
        size += len(chunk)
    seconds = time.perf_counter() - t
    if traced:
        peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
    else:
        peak = max(0, _rss_kb("VmHWM") - rss_before) * 1024
    return log.frames, size, seconds, peak


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--days", type=float, default=30.0)
    ap.add_argument("--engine", default="sqlite", choices=["sqlite", "postgresql"])
    ap.add_argument("--pg", default=os.environ.get("EQGW_BENCH_PG", PG_DEFAULT))
    ap.add_argument("--formats", default=",".join(FORMATS))
    ap.add_argument(
        "--traced-days",
        default="1,3",
        help="spans (days, the last of the range) exported again under tracemalloc (slow)",
    )
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp, database(args.engine, Path(tmp), args.pg) as url:
        engine = create_engine(url)
        upgrade_engine(engine)
        t = time.perf_counter()
        frames, start, end = fill(engine, args.days)
        print(
            f"{args.engine}: {args.days:g} days of {VEHICLE}: {frames:,} frames packed in "
            f"{time.perf_counter() - t:.0f} s (read in pages of {archive.PAGE_S:.0f} s)"
        )
        spans = [float(d) for d in args.traced_days.split(",") if d]
        for fmt in args.formats.split(","):
            n, size, seconds, peak = export(engine, fmt, start, end, traced=False)
            traced = []
            for days in spans:
                _, tsize, _, tpeak = export(engine, fmt, end - days * 86400, end, traced=True)
                traced.append(f"{days:g} d ({tsize / 1e6:.1f} MB) {tpeak / 1e6:.1f} MB")
            print(
                f"{fmt:<8} {n:>10,} frames {size / 1e6:8.1f} MB in {seconds:5.0f} s; resident "
                f"peak +{peak / 1e6:.1f} MB | tracemalloc peak: {', '.join(traced)}"
            )
        engine.dispose()


if __name__ == "__main__":
    main()
