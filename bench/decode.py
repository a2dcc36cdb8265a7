"""Benchmark: `eqgw decode` against python-can's bare LogReader iteration of the same log.

Builds a candump -L log of at least 1,000,000 frames by tiling the realistic mixed fixture
(equalizer traffic of both series among other J1939 nodes, about 16 % equalizer records; the
voltages change in every repetition), and a
second one of equalizer traffic only (the worst case), then times, in one run and alternately:
  bare:   for msg in can.LogReader(path): pass
  decode: eqgw decode path --sa 30,31 > /dev/null   (in-process, the same code path as the CLI)
Goal (issue 2): decode at no less than 0.75 of the bare read rate.

    python -m bench.decode [--frames 1000000] [--rounds 2]
"""

from __future__ import annotations

import argparse
import contextlib
import os
import sys
import tempfile
import time
from pathlib import Path

import can

from app.cli import main as eqgw
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
        for label, eq_only in (("mixed bus (16 % equalizer)", False), ("equalizer only", True)):
            path = Path(tmp) / ("eq.log" if eq_only else "mixed.log")
            n = build_log(path, frames, eq_only)
            bare = min(time_bare(path) for _ in range(1))
            dec = float("inf")
            for _ in range(rounds):  # alternate so both see the same machine load
                bare = min(bare, time_bare(path))
                dec = min(dec, time_decode(path))
            bare_rate, dec_rate = n / bare, n / dec
            print(f"{label}: {n:,} frames, {path.stat().st_size / 1e6:.0f} MB")
            print(f"  python-can LogReader (bare): {bare_rate:>10,.0f} frames/s  ({bare:.2f} s)")
            print(f"  eqgw decode:                 {dec_rate:>10,.0f} frames/s  ({dec:.2f} s)")
            print(f"  ratio decode/bare: {dec_rate / bare_rate:.2f}  (goal >= 0.75)")


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=1_000_000)
    ap.add_argument("--rounds", type=int, default=2)
    args = ap.parse_args()
    run(args.frames, args.rounds)
