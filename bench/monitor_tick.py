"""Benchmark: one tick of the ingest monitors (offline, parked, vehicle states) over a fleet.

The pipeline ticks once a second: every unit's monitor (offline or parked, stale DM1) and,
when a websocket or the alert engine listens, every vehicle's state (`vehicle_state` events).
Prints the best of `--rounds` ticks for `--vehicles` vehicles of two units each, with and
without a `vehicle_state` subscriber.

    python -m bench.monitor_tick [--vehicles 500] [--rounds 30]
"""

from __future__ import annotations

import argparse
import time

import can

from eqgw.ingest import events
from eqgw.ingest.hub import EventHub
from eqgw.ingest.pipeline import BusBinding, IngestPipeline
from eqgw.protocol.encode import encode

VOLTAGES = {"v12": 12.5, "v24": 25.0, "i12": 1.0, "i24": 2.0}


def best_tick(vehicles: int, rounds: int, *, subscribed: bool) -> float:
    hub = EventHub(1_000_000)
    if subscribed:
        hub.subscribe({events.VEHICLE_STATE})
    bindings = [BusBinding(f"V{i}/can0", f"V{i}", (30, 31)) for i in range(vehicles)]
    pipeline = IngestPipeline(bindings, hub=hub)
    frames = [
        can.Message(timestamp=1000.0, arbitration_id=can_id, data=data, channel=b.bus)
        for b in bindings
        for sa in (30, 31)
        for can_id, data in encode("voltages", VOLTAGES, sa=sa)
    ]
    pipeline.process_many(frames)
    best = float("inf")
    for k in range(rounds):
        t = time.perf_counter()
        pipeline.tick(1001.0 + k * 0.01)
        best = min(best, time.perf_counter() - t)
    return best


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--vehicles", type=int, default=500)
    ap.add_argument("--rounds", type=int, default=30)
    args = ap.parse_args()
    bare = best_tick(args.vehicles, args.rounds, subscribed=False)
    full = best_tick(args.vehicles, args.rounds, subscribed=True)
    print(
        f"monitor tick, {args.vehicles} vehicles / {2 * args.vehicles} units: "
        f"{bare * 1000:.2f} ms (units only), {full * 1000:.2f} ms (with vehicle states)"
    )


if __name__ == "__main__":
    main()
