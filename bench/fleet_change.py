"""Vehicles changed without a restart: seconds from an API call to every gateway acting on it.

Usage: python -m bench.fleet_change [--rounds 5] [--db URL]

In a fresh schema of the PostgreSQL server (`--db`, default the test server on
127.0.0.1:5432): one `eqgw simulate` subprocess serves three vehicles over socketcand, a fleet
file seeds two of them, and two `eqgw serve` subprocesses share the buses. Each round adds the
third vehicle through gateway A's API and times, from the POST: the bus leased by one gateway,
its first frames (a unit heard after the POST, through the owner's API), gateway B on the new
fleet version; then renames its bus through B's API (the frames on the new bus), and deletes it
through A's API (the bus closed on both). For comparison, the time one gateway takes to stop
and start again (what adding a vehicle cost when the fleet file was read at start only).
Everything (simulator, gateways, PostgreSQL) shares this machine's cores.
"""

from __future__ import annotations

import argparse
import os
import statistics
import tempfile
import time
import uuid
from collections.abc import Callable
from pathlib import Path
from typing import Any

import httpx
from sqlalchemy import text

from eqgw.store.engine import create_engine
from tests.cluster_helpers import admin_key, readyz, start_gateway, start_simulator, write_fleet
from tests.proc_helpers import Process

DEFAULT_DB = os.environ.get("EQGW_TEST_PG", "postgresql+psycopg://postgres@127.0.0.1:5432/test")
SEEDED = ["SIM-001", "SIM-002"]
ADDED = "SIM-003"


def _until(cond: Callable[[], Any], timeout: float, what: str) -> float:
    """Poll `cond` every 20 ms; the time.time() it first held."""
    return _each({what: cond}, timeout)[what]


def _each(conds: dict[str, Callable[[], Any]], timeout: float) -> dict[str, float]:
    """Poll every condition in turn every 20 ms; the time.time() each first held."""
    deadline = time.monotonic() + timeout
    held: dict[str, float] = {}
    while len(held) < len(conds):
        for what, cond in conds.items():
            if what not in held and cond():
                held[what] = time.time()
        if time.monotonic() > deadline:
            raise SystemExit(f"timed out after {timeout:g} s waiting for {set(conds) - set(held)}")
        time.sleep(0.02)
    return held


def _owners(bases: list[str], bus: str) -> list[str]:
    out = []
    for base in bases:
        c = (readyz(base) or {}).get("cluster") or {}
        if bus in c.get("owned", []):
            out.append(c["instance"])
    return out


def _reading(bases: list[str], bus: str) -> bool:
    return any(
        any(b["name"] == bus for b in (readyz(base) or {}).get("buses") or []) for base in bases
    )


def _heard(base: str, auth: dict[str, str], bus: str, after: float) -> bool:
    r = httpx.get(f"{base}/api/v1/vehicles/{ADDED}/live", headers=auth, timeout=10)
    if r.status_code != 200:
        return False
    return any(u.get("bus") == bus and (u.get("last_seen") or 0) > after for u in r.json()["units"])


def run(db: str, rounds: int) -> None:
    schema = f"bench_{uuid.uuid4().hex[:10]}"
    admin = create_engine(db)
    with admin.begin() as conn:
        conn.execute(text(f'CREATE SCHEMA "{schema}"'))
    url = f"{db}?options=-csearch_path%3D{schema}"
    procs: list[Process] = []
    try:
        key = admin_key(url, "bench")
        auth = {"Authorization": f"Bearer {key}"}
        tmp = Path(tempfile.mkdtemp(prefix="eqgw-fleet-"))
        sim, port = start_simulator(tmp, 3)
        procs.append(sim)
        fleet = write_fleet(tmp / "fleet.toml", SEEDED, port)
        gws = {}
        for name in ("gw-a", "gw-b"):
            proc, base = start_gateway(tmp, url, fleet, name)
            procs.append(proc)
            gws[name] = (proc, base)
        a, b = gws["gw-a"][1], gws["gw-b"][1]
        bases = [a, b]
        _until(lambda: all(_owners(bases, bus) for bus in SEEDED), 180, "the seeded buses")
        bus = {"name": ADDED, "interface": "socketcand", "channel": ADDED,
               "options": {"host": "127.0.0.1", "port": port}}  # fmt: skip
        figures: dict[str, list[float]] = {k: [] for k in ("leased", "frames", "b_version",
                                                           "patch", "delete")}  # fmt: skip
        for i in range(rounds):
            t0 = time.time()
            r = httpx.post(f"{a}/api/v1/vehicles", headers=auth, timeout=30,
                           json={"id": ADDED, "depot": "North", "buses": [bus]})  # fmt: skip
            r.raise_for_status()
            version = r.json()["version"]
            seen = _each(
                {
                    "leased": lambda: len(_owners(bases, ADDED)) == 1,
                    "frames": lambda t=t0: any(_heard(x, auth, ADDED, t) for x in bases),
                    "b_version": lambda v=version: (
                        ((readyz(b) or {}).get("fleet") or {}).get("version", 0) >= v
                    ),
                },
                30,
            )
            leased, frames, b_on = seen["leased"], seen["frames"], seen["b_version"]
            t1 = time.time()
            renamed = f"{ADDED}/r{i}"
            r = httpx.patch(f"{b}/api/v1/vehicles/{ADDED}", headers=auth, timeout=30,
                            json={"buses": [{**bus, "name": renamed}]})  # fmt: skip
            r.raise_for_status()
            patched = _until(lambda n=renamed, t=t1: any(_heard(x, auth, n, t) for x in bases),
                             30, "frames on the renamed bus")  # fmt: skip
            t2 = time.time()
            httpx.delete(f"{a}/api/v1/vehicles/{ADDED}", headers=auth, timeout=30)
            closed = _until(lambda n=renamed: not _owners(bases, n) and not _reading(bases, n),
                            30, "the bus closed")  # fmt: skip
            row = {
                "leased": leased - t0,
                "frames": frames - t0,
                "b_version": b_on - t0,
                "patch": patched - t1,
                "delete": closed - t2,
            }
            for k, v in row.items():
                figures[k].append(v)
            print(
                f"round {i + 1}: POST -> leased {row['leased']:.2f} s, -> frames "
                f"{row['frames']:.2f} s, -> gateway B on the new version {row['b_version']:.2f} "
                f"s; PATCH (bus renamed) -> frames {row['patch']:.2f} s; DELETE -> closed on "
                f"both {row['delete']:.2f} s",
                flush=True,
            )
            time.sleep(1.0)
        # The old way: a gateway stopped and started again (with its buses read again).
        proc, _ = gws["gw-b"]
        t3 = time.time()
        proc.stop()
        proc, base = start_gateway(tmp, url, fleet, "gw-b2")
        procs.append(proc)
        _until(lambda: (readyz(base) or {}).get("ready"), 180, "B restarted")
        restart = time.time() - t3
        print("\nmedians over", rounds, "rounds:")
        for k, what in (
            ("leased", "POST -> the bus leased by one gateway"),
            ("frames", "POST -> its first frames"),
            ("b_version", "POST -> the other gateway on the new fleet version"),
            ("patch", "PATCH (bus renamed) -> frames on the new bus"),
            ("delete", "DELETE -> the bus closed on both gateways"),
        ):
            vals = figures[k]
            print(f"  {what:55s} {statistics.median(vals):5.2f} s (max {max(vals):.2f})")
        print(f"  {'a gateway stopped and started again (ready)':55s} {restart:5.2f} s")
    finally:
        for proc in reversed(procs):
            if proc.proc.poll() is None:
                proc.stop()
        with admin.begin() as conn:
            conn.execute(text(f'DROP SCHEMA "{schema}" CASCADE'))
        admin.dispose()


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--rounds", type=int, default=5)
    p.add_argument("--db", default=DEFAULT_DB, help="PostgreSQL server URL (a schema is made)")
    args = p.parse_args()
    run(args.db, args.rounds)


if __name__ == "__main__":
    main()
