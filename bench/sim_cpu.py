"""CPU per simulated vehicle: process CPU time of a real-time fleet run, at several speeds.

    python bench/sim_cpu.py --vehicles 20 --seconds 10 --speeds 1 10 --background-traffic

Runs the simulator alone (python-can virtual buses, one reader per bus draining what the fleet
sends, as a gateway or the socketcand server would), on a RealtimeClock, and prints the CPU
seconds per wall second, in total and per vehicle.
"""

from __future__ import annotations

import argparse
import asyncio
import sys
import time
from pathlib import Path

import can

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from eqgw.sim.clock import RealtimeClock
from eqgw.sim.fleet import SimulatedFleet


async def measure(
    vehicles: int, seconds: float, speed: float, background: bool, readers: bool
) -> dict[str, float]:
    fleet = SimulatedFleet(
        vehicles, seed=0, clock=RealtimeClock(speed), background_traffic=background
    )
    buses = (
        [can.Bus(interface="virtual", channel=ch) for ch in fleet.channels.values()]
        if readers
        else []
    )
    frames = 0
    try:
        await fleet.start()
        wall0, cpu0 = time.perf_counter(), time.process_time()
        while time.perf_counter() - wall0 < seconds:
            await asyncio.sleep(0.05)
            for bus in buses:
                while bus.recv(timeout=0) is not None:
                    frames += 1
        wall = time.perf_counter() - wall0
        cpu = time.process_time() - cpu0
    finally:
        await fleet.stop()
        for bus in buses:
            bus.shutdown()
    return {"wall": wall, "cpu": cpu, "frames": frames, "sim": wall * speed}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--vehicles", type=int, default=20)
    parser.add_argument("--seconds", type=float, default=10.0, help="wall seconds per run")
    parser.add_argument("--speeds", type=float, nargs="+", default=[1.0, 10.0])
    parser.add_argument("--background-traffic", action="store_true")
    parser.add_argument("--no-readers", action="store_true", help="nobody drains the buses")
    args = parser.parse_args()
    print(
        f"simulator CPU, {args.vehicles} vehicles, {args.seconds:g} s wall per run"
        f"{', background traffic' if args.background_traffic else ''}"
        f"{', no readers' if args.no_readers else ''}"
    )
    print(f"{'speed':>6} {'frames/s':>9} {'CPU %':>7} {'CPU ms/s per vehicle':>21}")
    for speed in args.speeds:
        r = asyncio.run(
            measure(
                args.vehicles,
                args.seconds,
                speed,
                args.background_traffic,
                not args.no_readers,
            )
        )
        share = r["cpu"] / r["wall"]
        per_vehicle_ms = 1000.0 * share / args.vehicles
        print(
            f"{speed:>5g}x {r['frames'] / r['wall']:>9.0f} {100 * share:>6.1f}% "
            f"{per_vehicle_ms:>21.3f}"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
