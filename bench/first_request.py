"""First requests after a start: how long `eqgw serve --simulate 3`'s first API requests take
once `/readyz` says ready.

Usage: python -m bench.first_request [--rounds 3]

Each round starts `eqgw serve --simulate 3` on a fresh SQLite file, waits until `/readyz` is
200, then times a few GETs with the admin key, each path twice (the first is the one a lazily
built API makes slow). Prints each request's time per round.
"""

from __future__ import annotations

import argparse
import re
import tempfile
import time
from pathlib import Path

import httpx

from tests.proc_helpers import Process, eqgw, free_port, wait_until

PATHS = ("/api/v1/vehicles", "/api/v1/vehicles", "/api/v1/alerts", "/api/v1/alerts", "/metrics")
ADMIN_KEY = re.compile(r"^\s+(eqgw_\S+)\s*$", re.M)


def one_round(tmp: Path) -> list[tuple[str, int, float]]:
    tmp.mkdir()
    port = free_port()
    env = {"EQGW_DATABASE_URL": f"sqlite:///{tmp / 'eqgw.db'}", "EQGW_API_PORT": str(port)}
    gw = Process(eqgw("serve", "--simulate", "3"), tmp, env)
    base = f"http://127.0.0.1:{port}"

    def ready() -> bool:
        try:
            return httpx.get(f"{base}/readyz", timeout=5).status_code == 200
        except httpx.HTTPError:
            return False

    try:
        wait_until(ready, 120, "ready", interval=0.05)
        key = ADMIN_KEY.search(gw.output())
        assert key, gw.output()
        auth = {"Authorization": f"Bearer {key.group(1)}"}
        out = []
        for path in PATHS:
            start = time.perf_counter()
            r = httpx.get(base + path, headers=auth, timeout=30)
            out.append((path, r.status_code, time.perf_counter() - start))
        return out
    finally:
        gw.stop()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=3)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        for i in range(args.rounds):
            print(f"round {i + 1}:")
            for path, status, took in one_round(Path(tmp) / f"round{i}"):
                print(f"  GET {path:20s} {status}  {took * 1000:7.1f} ms")


if __name__ == "__main__":
    main()
