"""Bus opening: how long a real `eqgw serve` takes to open 500 buses on one socketcand server.

Usage: python -m bench.bus_open [--buses 500] [--concurrency 16]

Starts `eqgw simulate --vehicles N` (one socketcand server, N buses), a counting proxy in front
of it (tests/socketcand_proxy.py) and `eqgw serve` with one socketcand bus per vehicle, all on
that server, `EQGW_BUS_OPEN_CONCURRENCY` as given. Prints, every 2 s and at the end, how many
buses `/readyz` reports open, the most opens the server side saw at once, and the seconds from
the gateway's start until every bus was open.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

from tests.cluster_helpers import LISTENING, start_gateway
from tests.proc_helpers import Process, eqgw
from tests.socketcand_proxy import OpeningCounter
from tests.test_bus_open_processes import buses_open, fleet_file


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--buses", type=int, default=500)
    parser.add_argument("--concurrency", type=int, default=16)
    parser.add_argument("--timeout", type=float, default=300.0)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp_name:
        tmp = Path(tmp_name)
        sim = Process(
            eqgw("simulate", "--vehicles", str(args.buses), "--listen", "127.0.0.1:0"), tmp
        )
        proxy: OpeningCounter | None = None
        gw: Process | None = None
        try:
            sim_port = int(sim.wait_line(LISTENING, timeout=300).group(2))
            proxy = OpeningCounter(("127.0.0.1", sim_port)).start()
            fleet = fleet_file(tmp / "fleet.toml", args.buses, proxy.port)
            env = {"EQGW_BUS_OPEN_CONCURRENCY": str(args.concurrency)}
            start = time.monotonic()
            gw, base = start_gateway(
                tmp, f"sqlite:///{tmp / 'eqgw.db'}", fleet, "bench", extra_env=env
            )
            n = 0
            first: float | None = None  # when the first open was asked (within 0.1 s)
            shown = 0.0
            while time.monotonic() - start < args.timeout:
                if first is None and proxy.max_opening:
                    first = time.monotonic()
                if time.monotonic() - shown >= 2.0:
                    shown = time.monotonic()
                    n = buses_open(base)
                    print(f"{shown - start:6.1f} s: {n:4d}/{args.buses} open, at most "
                          f"{proxy.max_opening} opening at once")  # fmt: skip
                    if n == args.buses:
                        break
                time.sleep(0.1)
            took = time.monotonic() - start
            verdict = "all open" if n == args.buses else f"only {n} open"
            since_first = f"{time.monotonic() - first:.1f} s" if first is not None else "-"
            print(
                f"{args.buses} buses, concurrency {args.concurrency}: {verdict} "
                f"{took:.1f} s after the gateway started, {since_first} after its first open "
                f"(within 2 s); at most {proxy.max_opening} opening at once, "
                f"{proxy.opened} opens answered"
            )
        finally:
            for proc in (gw, sim):
                if proc is not None and proc.proc.poll() is None:
                    proc.stop()
            if proxy is not None:
                proxy.stop()


if __name__ == "__main__":
    main()
