"""Shutdown benchmark: how long `eqgw serve --simulate 3` takes from SIGTERM to exit, under load.

Usage: python -m bench.shutdown [--rounds 20]

Each round starts `eqgw serve --simulate 3` on a fresh SQLite file, loads it for 1-4 s (three
clients reading the fleet and posting requests the gateway delivers on the bus), sends SIGTERM
and times the exit. Prints every round (seconds, exit code, whether the ingest's final flush
said it wrote every row) and min / median / max. The bound is EQGW_API_SHUTDOWN_TIMEOUT_S (9 s):
a shutdown still running then is ended by the watchdog (exit 3, its stacks on stderr).
"""

from __future__ import annotations

import argparse
import random
import statistics
import tempfile
from pathlib import Path

from tests.test_shutdown import FLUSHED, sigterm_round


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=20)
    args = parser.parse_args()
    rng = random.Random(1)
    times: list[float] = []
    bad = 0
    with tempfile.TemporaryDirectory() as tmp:
        for i in range(args.rounds):
            elapsed, rc, out = sigterm_round(Path(tmp) / f"round{i}", rng.uniform(1.0, 4.0))
            flushed = FLUSHED in out
            bad += rc not in (0, -15) or not flushed
            times.append(elapsed)
            print(f"round {i + 1:3d}: {elapsed:5.2f} s  exit {rc}  final flush done: {flushed}")
    print(
        f"{args.rounds} rounds: SIGTERM to exit min {min(times):.2f} s, median "
        f"{statistics.median(times):.2f} s, max {max(times):.2f} s; {bad} rounds not clean"
    )


if __name__ == "__main__":
    main()
