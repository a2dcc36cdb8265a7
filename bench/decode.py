"""Benchmark: `eqgw decode` against python-can's bare LogReader iteration of the same log.

Builds a candump -L log of at least 1,000,000 frames by tiling the realistic mixed fixture
(equalizer traffic of both series among other J1939 nodes, about 16 % equalizer records; the
voltages change in every repetition), and a
second one of equalizer traffic only (the worst case), then times both side by side, round
after round (each round: bare then decode on the mixed log, then on the equalizer-only log):
  bare:   for msg in can.LogReader(path): pass
  decode: eqgw decode path --sa 30,31 > /dev/null   (in-process, the same code path as the CLI)
Goal: decode at no less than 0.75 of the bare read rate on both logs. Prints every round's
ratios, then each log's best rates and the median, min and max ratio.

    python -m bench.decode [--frames 1000000] [--rounds 5]
"""

from __future__ import annotations

import argparse
import contextlib
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

import can

from eqgw.cli import main as eqgw
from tests.fixtures import mixed_log


def vary(msg: can.Message) -> bool:
    """An equalizer voltages frame with both voltage bytes."""
    cid = msg.arbitration_id
    return (
        msg.is_extended_id
        and (cid >> 8) & 0xFFFF == 0xFFD6
        and cid & 0xFF in (30, 31)
        and len(msg.data) >= 2
    )


def build_log(path: Path, frames: int, equalizer_only: bool) -> int:
    base = list(can.LogReader(str(mixed_log.LOG)))
    if equalizer_only:
        base = [m for m in base if m.is_extended_id and (m.arbitration_id & 0xFF) in (30, 31)]
    span = base[-1].timestamp - base[0].timestamp + 1.0
    written = 0
    with can.CanutilsLogWriter(str(path)) as writer:
        rep = 0
        while written < frames:
            for msg in base:
                data = bytes(msg.data)
                if vary(msg):
                    # New voltages every repetition, so no cache sees the same payload twice.
                    v12 = (int.from_bytes(data[:2], "little") + rep) % 0xFB00
                    data = v12.to_bytes(2, "little") + data[2:]
                writer.on_message_received(
                    can.Message(
                        timestamp=msg.timestamp + rep * span,
                        arbitration_id=msg.arbitration_id,
                        is_extended_id=msg.is_extended_id,
                        data=data,
                        dlc=msg.dlc,
                        channel=msg.channel,
                    )
                )
                written += 1
                if written >= frames:
                    break
            rep += 1
    return written


def time_bare(path: Path) -> float:
    start = time.perf_counter()
    n = 0
    for _ in can.LogReader(str(path)):
        n += 1
    return time.perf_counter() - start


def time_decode(path: Path) -> float:
    start = time.perf_counter()
    with open(os.devnull, "w") as devnull, contextlib.redirect_stdout(devnull):
        saved_err = sys.stderr
        sys.stderr = devnull
        try:
            rc = eqgw(["decode", str(path), "--sa", "30,31"])
        finally:
            sys.stderr = saved_err
    assert rc == 0
    return time.perf_counter() - start


def run(frames: int, rounds: int) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        logs = []
        for label, eq_only in (("mixed bus (16 % equalizer)", False), ("equalizer only", True)):
            path = Path(tmp) / ("eq.log" if eq_only else "mixed.log")
            n = build_log(path, frames, eq_only)
            logs.append((label, path, n))
            print(f"{label}: {n:,} frames, {path.stat().st_size / 1e6:.0f} MB")
        time_bare(logs[0][1])  # warm the file cache and the imports
        ratios: dict[str, list[float]] = {label: [] for label, _, _ in logs}
        best: dict[str, tuple[float, float]] = {}
        for r in range(1, rounds + 1):
            # Side by side: each round times both logs, bare then decode, on the same load.
            parts = []
            for label, path, n in logs:
                bare = time_bare(path)
                dec = time_decode(path)
                ratios[label].append(bare / dec)
                b0, d0 = best.get(label, (bare, dec))
                best[label] = (min(b0, bare), min(d0, dec))
                parts.append(
                    f"{label.split(' ')[0]}: bare {n / bare:,.0f}, decode {n / dec:,.0f} frames/s, "
                    f"ratio {bare / dec:.2f}"
                )
            print(f"round {r}: " + "; ".join(parts))
        for label, _, n in logs:
            bare, dec = best[label]
            rs = sorted(ratios[label])
            print(f"{label}:")
            print(
                f"  python-can LogReader (bare): {n / bare:>10,.0f} frames/s  (best {bare:.2f} s)"
            )
            print(f"  eqgw decode:                 {n / dec:>10,.0f} frames/s  (best {dec:.2f} s)")
            print(
                f"  ratio decode/bare: median {statistics.median(rs):.2f}, "
                f"min {rs[0]:.2f}, max {rs[-1]:.2f} over {len(rs)} rounds  (goal >= 0.75)"
            )


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=1_000_000)
    ap.add_argument("--rounds", type=int, default=5)
    args = ap.parse_args()
    run(args.frames, args.rounds)
