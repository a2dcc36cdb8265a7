"""A database path blackholed (packets dropped, no reset): how soon `eqgw serve` answers 503,
journals its rows, and fences, and how soon another gateway takes its bus.

Usage: python -m bench.faults [--rounds 3] [--db postgresql+psycopg://postgres@127.0.0.1:5432/test]

Each round uses a fresh schema of the PostgreSQL server, `eqgw simulate` over socketcand and a
TCP proxy (tests/proxy_helpers.py) that, at the fault, stops forwarding bytes both ways while
keeping every connection open. Single gateway (`EQGW_CLUSTER_MODE=off`, default settings
otherwise): the time from the fault to the answer of a request that needs the database (a
503), and to the first rows in the writer's journal. Two gateways (cluster mode, lease period
0.5 s, lease timeout 2 s, the rest default), the first one through the proxy: the time from
the fault to its fence, and to the other gateway owning its bus.
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
import uuid
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import httpx
from sqlalchemy import text

from eqgw.store.engine import create_engine
from tests.cluster_helpers import (
    METRICS_TOKEN,
    operator_key,
    readyz,
    start_gateway,
    start_simulator,
    write_fleet,
)
from tests.proc_helpers import Process, eqgw, free_port
from tests.proxy_helpers import blackhole_proxy
from tests.test_durability import SERVING


def _poll(cond: Callable[[], Any], timeout: float, what: str) -> Any:
    deadline = time.monotonic() + timeout
    while True:
        value = cond()
        if value:
            return value
        if time.monotonic() > deadline:
            raise RuntimeError(f"timed out waiting for {what}")
        time.sleep(0.05)


@contextmanager
def _schema(db: str) -> Iterator[str]:
    name = f"bench_{uuid.uuid4().hex[:10]}"
    admin = create_engine(db)
    with admin.begin() as conn:
        conn.execute(text(f'CREATE SCHEMA "{name}"'))
    try:
        yield f"{db}?options=-csearch_path%3D{name}"
    finally:
        with admin.begin() as conn:
            conn.execute(text(f'DROP SCHEMA "{name}" CASCADE'))
        admin.dispose()


def single(db: str) -> tuple[float, float]:
    """(s from the fault to a 503, s from the fault to rows in the journal)."""
    with tempfile.TemporaryDirectory() as d, _schema(db) as url:
        tmp = Path(d)
        key = operator_key(url, "bench")
        sim, port = start_simulator(tmp, 2)
        fleet = write_fleet(tmp / "fleet.toml", ["SIM-001", "SIM-002"], port)
        with blackhole_proxy(url) as proxy:
            api_port = free_port()
            gw = Process(
                eqgw("serve", "--config", str(fleet)),
                tmp,
                {
                    "EQGW_DATABASE_URL": proxy.url(url),
                    "EQGW_CLUSTER_MODE": "off",
                    "EQGW_API_PORT": str(api_port),
                    "EQGW_API_METRICS_TOKEN": METRICS_TOKEN,
                },
            )
            try:
                gw.wait_line(SERVING, timeout=120)
                base = f"http://127.0.0.1:{api_port}"
                auth = {"Authorization": f"Bearer {key}"}
                _poll(
                    lambda: (b := readyz(base)) and b["database"]["writer"]["state"] == "idle",
                    60,
                    "a first commit",
                )
                time.sleep(1.0)
                fault = proxy.blackhole()
                # The key was never used: its lookup is the request's first database work.
                r = httpx.get(f"{base}/api/v1/vehicles/SIM-001/faults", headers=auth, timeout=60)
                answered = time.time() - fault
                if r.status_code != 503:
                    raise RuntimeError(f"expected a 503, got {r.status_code}: {r.text}")
                _poll(
                    lambda: (b := readyz(base)) and b["database"]["writer"]["journal_rows"] > 0,
                    120,
                    "rows in the journal",
                )
                journaled = time.time() - fault
            finally:
                gw.stop()
                sim.stop()
        return answered, journaled


def pair(db: str) -> tuple[float, float]:
    """(s from the fault to the cut-off gateway's fence, s to the other owning its bus)."""
    with tempfile.TemporaryDirectory() as d, _schema(db) as url:
        tmp = Path(d)
        operator_key(url, "bench")  # migrated before either starts
        sim, port = start_simulator(tmp, 1)
        fleet = write_fleet(tmp / "fleet.toml", ["SIM-001"], port)
        with blackhole_proxy(url) as proxy:
            a, a_base = start_gateway(tmp, proxy.url(url), fleet, "gw-a")
            b: Process | None = None
            try:
                a.wait_line(SERVING, timeout=120)
                _poll(lambda: (r := readyz(a_base)) and r["cluster"]["owned"], 60, "A owns")
                b, b_base = start_gateway(tmp, url, fleet, "gw-b")
                b.wait_line(SERVING, timeout=120)
                _poll(
                    lambda: (r := readyz(b_base)) and len(r["cluster"]["instances"]) == 2,
                    60,
                    "B sees A",
                )
                time.sleep(1.0)
                fault = proxy.blackhole()
                took = _poll(
                    lambda: (r := readyz(b_base)) and r["cluster"]["owned_since"].get("SIM-001"),
                    120,
                    "B to take the bus",
                )
                fenced = _poll(
                    lambda: (r := readyz(a_base)) and r["cluster"]["last_fence_at"], 30, "A fenced"
                )
            finally:
                for p in (b, a):
                    if p is not None:
                        p.stop()
                sim.stop()
        return fenced - fault, took - fault


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--db", default="postgresql+psycopg://postgres@127.0.0.1:5432/test")
    args = ap.parse_args()
    answers, journals, fences, takeovers = [], [], [], []
    for i in range(1, args.rounds + 1):
        answered, journaled = single(args.db)
        answers.append(answered)
        journals.append(journaled)
        print(
            f"single gateway  round {i}: fault -> 503 {answered:5.2f} s, "
            f"fault -> rows in the journal {journaled:5.2f} s",
            flush=True,
        )
    for i in range(1, args.rounds + 1):
        fenced, took = pair(args.db)
        fences.append(fenced)
        takeovers.append(took)
        print(
            f"two gateways    round {i}: fault -> A fenced {fenced:5.2f} s, "
            f"fault -> B owns A's bus {took:5.2f} s",
            flush=True,
        )
    for name, values in (
        ("fault -> 503", answers),
        ("fault -> journal", journals),
        ("fault -> fence", fences),
        ("fault -> takeover", takeovers),
    ):
        print(f"{name:18} median {statistics.median(values):5.2f} s, worst {max(values):5.2f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
