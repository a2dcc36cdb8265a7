"""What a SIGKILL of `eqgw serve` loses: seconds of frames, with PostgreSQL up and during an outage.

Usage: python -m bench.kill_loss [--rounds 3] [--vehicles 4]

Runs a private PostgreSQL cluster (initdb in a temp dir, as tests/test_ingest_outage.py does),
`eqgw simulate --record` and `eqgw serve` (default settings: cluster mode auto, flush 0.5 s,
journal on). Each round SIGKILLs the gateway, either with the database up or 8 s into an
outage (the database is started again after the kill), starts a new gateway, lets it run, and
compares the simulator's record of every frame it sent with the raw archive: the frames sent
before the kill and missing are the loss, reported as the span from the oldest missing one to
the kill (0 when none is missing) and as a count.
"""

from __future__ import annotations

import argparse
import glob
import shutil
import statistics
import tempfile
import time
from pathlib import Path

from tests.test_durability import Rig, lost_frames
from tests.test_ingest_outage import ThrowawayCluster


def _round(tmp: Path, outage: bool, vehicles: int) -> tuple[float, int, int]:
    cluster = ThrowawayCluster(sorted(glob.glob("/usr/lib/postgresql/*/bin"))[-1])
    cluster.init()
    cluster.start()
    rig = Rig(tmp, cluster, vehicles=vehicles)
    try:
        rig.start_gateway()
        start = time.time()
        deadline = time.monotonic() + 90
        while not rig.committed_after(start):
            if time.monotonic() > deadline:
                raise RuntimeError("the gateway never committed")
            time.sleep(0.1)
        time.sleep(5.0)
        if outage:
            cluster.stop()
            time.sleep(8.0)
        killed = time.time()
        assert rig.gw is not None
        rig.gw.kill()
        if outage:
            cluster.start()
        rig.start_gateway()
        later = time.time() + 2
        while not rig.committed_after(later):
            time.sleep(0.1)
        rig.gw.stop()
        rig.sim.stop()
        lost, sent, missing = lost_frames(rig, [(start, killed)], limit=None)
        span = killed - min(f[2] for f in missing) if missing else 0.0
        return span, lost, sent
    finally:
        rig.close()
        cluster.destroy()


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--vehicles", type=int, default=4)
    args = ap.parse_args()
    for outage in (False, True):
        spans = []
        for i in range(args.rounds):
            tmp = Path(tempfile.mkdtemp(prefix="eqgw-kill-"))
            try:
                span, lost, sent = _round(tmp, outage, args.vehicles)
            finally:
                shutil.rmtree(tmp, ignore_errors=True)
            spans.append(span)
            what = "8 s into an outage" if outage else "database up"
            print(
                f"SIGKILL, {what:<18} round {i + 1}: last {span:.2f} s of frames lost "
                f"({lost} of {sent} frames sent before the kill)",
                flush=True,
            )
        print(f"    median {statistics.median(spans):.2f} s, worst {max(spans):.2f} s", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
