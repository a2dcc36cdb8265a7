"""What a row held by the writer costs: memory while the database is away, disk in the journal.

Usage: python -m bench.held_rows [--copies 20]

Decodes the realistic fixture (tests/fixtures/mixed_bus.log: two vehicles, three equalizers,
two minutes) tiled `--copies` times through the live pipeline, raw archive on and off, and
hands every row to a writer that is never started (as while the database is away), then
reports the growth per row held: tracemalloc's (the rows, their payloads, the writer's deque)
and the process's resident memory (allocator overhead included; in a fresh process, without
tracing), and the journal file's bytes per row once the same rows are spilled to it.
"""

from __future__ import annotations

import argparse
import gc
import os
import subprocess
import sys
import tempfile
import tracemalloc
from typing import Any

import can

from bench.replay import BUSES, FIXTURE, SPAN_S, VEHICLE_CFG
from eqgw.config import Settings, WriterSettings
from eqgw.ingest.journal import RowJournal
from eqgw.ingest.pipeline import BusBinding, IngestPipeline
from eqgw.ingest.writer import BatchedWriter
from eqgw.store.engine import create_engine


def _frames(copies: int) -> list[can.Message]:
    base = list(can.LogReader(str(FIXTURE)))
    out = []
    for i in range(copies):
        for m in base:
            out.append(
                can.Message(
                    timestamp=m.timestamp + i * SPAN_S,
                    arbitration_id=m.arbitration_id,
                    data=m.data,
                    is_extended_id=m.is_extended_id,
                    channel=m.channel,
                )
            )
    return out


def _rss() -> int:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")


def measure(frames: list[can.Message], raw_archive: bool, *, trace: bool) -> dict[str, Any]:
    settings = Settings(database_url="sqlite://", buses=BUSES, vehicles=VEHICLE_CFG)
    bindings = [BusBinding(b.name, b.vehicle_id, tuple(b.equalizer_sas)) for b in settings.buses]
    pipeline = IngestPipeline(
        bindings,
        channel_map={"can0": "BUS-101/can0", "can1": "BUS-102/can1"},
        raw_archive=raw_archive,
    )
    engine = create_engine("sqlite://")
    writer = BatchedWriter(engine, WriterSettings(max_pending_rows=100_000_000))
    gc.collect()
    if trace:
        tracemalloc.start()
    before = tracemalloc.get_traced_memory()[0] if trace else _rss()
    kinds: dict[str, int] = {}
    for i in range(0, len(frames), 1000):
        pipeline.process_many(frames[i : i + 1000])
        rows = pipeline.take_rows()
        for row in rows:
            kinds[row.kind] = kinds.get(row.kind, 0) + 1
        assert writer.offer(rows)
    gc.collect()
    if trace:
        held = tracemalloc.get_traced_memory()[0] - before
        tracemalloc.stop()
    else:
        held = _rss() - before
    n = writer.pending
    items = list(writer._queue)  # the rows as held, for the journal
    with tempfile.TemporaryDirectory() as tmp:
        journal = RowJournal.open(tmp, "postgresql://bench@localhost/bench")
        journal.append(items)
        disk = journal.size_bytes()
        journal.close(remove=True)
    engine.dispose()
    return {"rows": n, "memory": held, "disk": disk, "kinds": kinds}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--copies", type=int, default=20, help="fixture copies (2 min each)")
    ap.add_argument("--rss-of", choices=["on", "off"], help=argparse.SUPPRESS)
    args = ap.parse_args()
    frames = _frames(args.copies)
    if args.rss_of:  # a fresh process: its resident memory grows by what it holds
        r = measure(frames, args.rss_of == "on", trace=False)
        print(r["memory"] / r["rows"])
        return 0
    print(f"{len(frames):,} frames, {args.copies * SPAN_S / 60:.0f} min of 2 vehicles")
    for raw in (True, False):
        child = [sys.executable, "-m", "bench.held_rows", "--copies", str(args.copies)]
        out = subprocess.run(
            [*child, "--rss-of", "on" if raw else "off"], capture_output=True, text=True, check=True
        )
        rss = float(out.stdout.split()[-1])
        r = measure(frames, raw, trace=True)
        mix = ", ".join(f"{k} {v:,}" for k, v in sorted(r["kinds"].items(), key=lambda x: -x[1]))
        print(
            f"raw archive {'on ' if raw else 'off'}: {r['rows']:>9,} rows held  "
            f"memory {r['memory'] / r['rows']:>5.0f} B/row (Python objects), "
            f"{rss:>5.0f} B/row (process RSS growth)  "
            f"journal {r['disk'] / r['rows']:>5.0f} B/row"
        )
        print(f"    rows: {mix}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
