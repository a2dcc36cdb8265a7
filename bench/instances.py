"""Several gateways on one PostgreSQL: records/s ingested with 1, 2 and 4 `eqgw serve`.

Usage: python -m bench.instances [--vehicles 40] [--speed 50] [--seconds 20] [--instances 1 2 4]

For each gateway count, in a fresh schema of the PostgreSQL server (`--db`, default the test
server on 127.0.0.1:5432): one `eqgw simulate` subprocess serves `--vehicles` buses over
socketcand at `--speed` times real time (so a few dozen simulated vehicles offer the traffic of
thousands), N `eqgw serve` subprocesses share the buses through their leases; once every bus is
read and the leases are balanced, the decoded records (the gateways' /metrics) and the rows
committed to PostgreSQL are counted over `--seconds`. Baselines in the same run: the bare
PostgreSQL COPY rate of measurement rows (what the database alone takes on this machine) and
the traffic the simulator offers (records/s per simulated vehicle at 1x). Prints the figures
and a capacity-planning table. Everything (simulator, gateways, PostgreSQL) shares this
machine's cores, so more gateways cannot add more CPU than the machine has.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import re
import subprocess
import sys
import tempfile
import time
import uuid
from pathlib import Path
from typing import Any

import httpx
import psycopg
from sqlalchemy import text

from eqgw.store import archive
from eqgw.store.engine import create_engine
from eqgw.store.migrate import upgrade_engine
from eqgw.store.models import RAW_TABLES
from tests.cluster_helpers import write_fleet
from tests.proc_helpers import free_port, terminate

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_DB = os.environ.get("EQGW_TEST_PG", "postgresql+psycopg://postgres@127.0.0.1:5432/test")
# Rows of the time series; the raw archive counted in frames (packed or not yet).
ROW_TABLES = tuple(t.name for t in RAW_TABLES if t.name not in ("raw_blocks", "raw_recent"))
METRIC = re.compile(r"^eqgw_records_total (\S+)$", re.M)
PENDING = re.compile(r"^eqgw_writer_pending_rows (\S+)$", re.M)
DROPS = re.compile(r"^eqgw_bus_drops_total\{[^}]*\} (\S+)$", re.M)


# /readyz details and per-bus metrics need the metrics token (or an admin key).
METRICS_TOKEN = "bench-metrics"
METRICS_AUTH = {"Authorization": f"Bearer {METRICS_TOKEN}"}


def _spawn(args: list[str], env: dict[str, str], cwd: Path, log: Path) -> subprocess.Popen[bytes]:
    return subprocess.Popen(
        [sys.executable, "-m", "eqgw.cli", *args],
        cwd=cwd,
        env={**env, "PYTHONPATH": str(ROOT), "PYTHONUNBUFFERED": "1"},
        stdout=log.open("wb"),
        stderr=subprocess.STDOUT,
    )


def _json(url: str) -> Any:
    try:
        return httpx.get(url, headers=METRICS_AUTH, timeout=10).json()
    except (httpx.HTTPError, ValueError):
        return None


def _records(bases: list[str]) -> float:
    total = 0.0
    for base in bases:
        body = httpx.get(f"{base}/metrics", headers=METRICS_AUTH, timeout=10).text
        m = METRIC.search(body)
        total += float(m.group(1)) if m else 0.0
    return total


def _lag(bases: list[str]) -> tuple[float, float]:
    """(rows waiting in the gateways' writers, frames their readers dropped)."""
    pending = drops = 0.0
    for base in bases:
        body = httpx.get(f"{base}/metrics", headers=METRICS_AUTH, timeout=10).text
        pending += sum(float(v) for v in PENDING.findall(body))
        drops += sum(float(v) for v in DROPS.findall(body))
    return pending, drops


def _rows(url: str) -> int:
    engine = create_engine(url)
    try:
        with engine.connect() as conn:
            return archive.count_frames(conn) + sum(
                int(conn.execute(text(f"SELECT count(*) FROM {t}")).scalar_one())
                for t in ROW_TABLES
            )
    finally:
        engine.dispose()


def copy_baseline(admin_url: str, rows: int = 200_000) -> float:
    """Rows/s of a bare COPY of measurement-shaped rows into an unlogged-free plain table."""
    from eqgw.cluster.leases import libpq_conninfo

    data = [(i % 50, 1.7e9 + i * 0.01, 12.6, 25.2, -3.5, 10.0) for i in range(rows)]
    with psycopg.connect(libpq_conninfo(admin_url)) as conn:
        conn.execute(
            "CREATE TEMP TABLE copy_bench (unit_id int, ts float8, v12 float8, v24 float8, "
            "i12 float8, i24 float8, PRIMARY KEY (unit_id, ts))"
        )
        t0 = time.perf_counter()
        with conn.cursor() as cur, cur.copy("COPY copy_bench FROM STDIN") as cp:
            for row in data:
                cp.write_row(row)
        conn.commit()
        return rows / (time.perf_counter() - t0)


def run(
    admin_url: str, n_instances: int, vehicles: int, speed: float, seconds: float, tmp: Path
) -> dict[str, float]:
    schema = f"bench_{uuid.uuid4().hex[:10]}"
    admin = create_engine(admin_url)
    with admin.begin() as conn:
        conn.execute(text(f'CREATE SCHEMA "{schema}"'))
    url = f"{admin_url}?options=-csearch_path%3D{schema}"
    procs: list[subprocess.Popen[bytes]] = []
    try:
        engine = create_engine(url)
        upgrade_engine(engine)
        engine.dispose()
        env = {k: v for k, v in os.environ.items() if not k.startswith("EQGW_")}
        sim_log = tmp / f"sim-{n_instances}.log"
        sim = _spawn(
            [
                "simulate",
                "--vehicles",
                str(vehicles),
                "--speed",
                str(speed),
                "--listen",
                "127.0.0.1:0",
            ],
            env,
            tmp,
            sim_log,
        )
        procs.append(sim)
        port = 0
        deadline = time.monotonic() + 60
        while not port and time.monotonic() < deadline:
            m = re.search(r"listening \S+:(\d+)", sim_log.read_text())
            port = int(m.group(1)) if m else 0
            time.sleep(0.2)
        if not port:
            raise RuntimeError(f"simulator did not start: {sim_log.read_text()[-2000:]}")
        fleet = tmp / f"fleet-{n_instances}.toml"
        write_fleet(fleet, [f"SIM-{i:03d}" for i in range(1, vehicles + 1)], port)
        bases = []
        for i in range(n_instances):
            api_port = free_port()
            genv = {
                **env,
                "EQGW_DATABASE_URL": url,
                "EQGW_API_PORT": str(api_port),
                "EQGW_CLUSTER_INSTANCE_ID": f"bench-{i + 1}",
                "EQGW_API_METRICS_TOKEN": METRICS_TOKEN,
                "EQGW_CLUSTER_LEASE_PERIOD_S": "1",
            }
            procs.append(_spawn(["serve", "--config", str(fleet)], genv, tmp, tmp / f"gw{i}.log"))
            bases.append(f"http://127.0.0.1:{api_port}")
        fair = vehicles // n_instances

        def settled(all_open: bool) -> bool:
            owned = []
            for base in bases:
                body = _json(f"{base}/readyz")
                if not body or "cluster" not in body:
                    return False
                if all_open and any(b["state"] != "open" for b in body["buses"]):
                    return False
                owned.append(len(body["cluster"]["owned"]))
            return sum(owned) == vehicles and min(owned) >= fair

        deadline = time.monotonic() + 180
        while not settled(all_open=False):
            if time.monotonic() > deadline:
                raise RuntimeError("gateways did not share the buses within 180 s")
            time.sleep(0.5)
        # Every bus open too; an overloaded simulator may be slow to accept one: go on after
        # a minute (its frames are simply not counted).
        deadline = time.monotonic() + 60
        while not settled(all_open=True) and time.monotonic() < deadline:
            time.sleep(0.5)
        time.sleep(5)  # warm up: every unit heard, writer batches flowing
        r0, w0, t0 = _records(bases), _rows(url), time.monotonic()
        time.sleep(seconds)
        r1, w1, t1 = _records(bases), _rows(url), time.monotonic()
        pending, drops = _lag(bases)
        el = t1 - t0
        return {
            "records_s": (r1 - r0) / el,
            "rows_s": (w1 - w0) / el,
            "pending": pending,
            "drops": drops,
        }
    finally:
        for p in reversed(procs):
            terminate(p)
        with admin.begin() as conn:
            conn.execute(text(f'DROP SCHEMA "{schema}" CASCADE'))
        admin.dispose()


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--db", default=DEFAULT_DB)
    ap.add_argument("--vehicles", type=int, default=40)
    ap.add_argument("--speed", type=float, default=50.0)
    ap.add_argument("--seconds", type=float, default=20.0)
    ap.add_argument("--instances", type=int, nargs="+", default=[1, 2, 4])
    args = ap.parse_args(argv)

    copy_rate = copy_baseline(args.db)
    print(f"baseline: bare PostgreSQL COPY of measurement rows   {copy_rate:>10,.0f} rows/s")
    print(
        f"fleet: {args.vehicles} simulated vehicles at {args.speed:g}x "
        f"(the traffic of {args.vehicles * args.speed:,.0f} vehicles at 1x), "
        f"{args.seconds:g} s per run"
    )
    results: dict[int, dict[str, float]] = {}
    with tempfile.TemporaryDirectory(prefix="eqgw-bench-inst-") as d:
        for n in args.instances:
            res = run(args.db, n, args.vehicles, args.speed, args.seconds, Path(d))
            results[n] = res
            ratio = res["records_s"] / results[args.instances[0]]["records_s"]
            print(
                f"{n} gateway{'s' if n > 1 else ' '}: {res['records_s']:>10,.0f} records/s  "
                f"{res['rows_s']:>10,.0f} rows/s committed  "
                f"({ratio:.2f}x the {args.instances[0]}-gateway run; writer backlog "
                f"{res['pending']:,.0f} rows, reader drops {res['drops']:,.0f})"
            )
    offered = max(r["records_s"] for r in results.values())
    per_vehicle = offered / (args.vehicles * args.speed)
    best_single = results.get(1, results[args.instances[0]])["records_s"]
    rows_per_record = max(r["rows_s"] / r["records_s"] for r in results.values() if r["records_s"])
    print(f"offered: {per_vehicle:.2f} records/s per vehicle at 1x (from the best run)")
    print()
    print("capacity (this machine; records/s per vehicle as simulated):")
    print("| | records/s | vehicles at 1x |")
    print("|---|---|---|")
    print(
        f"| one gateway (measured{', saturated' if best_single < 0.9 * offered else ''}) "
        f"| {best_single:,.0f} | {best_single / per_vehicle:,.0f} |"
    )
    pg_records = copy_rate / rows_per_record
    print(
        f"| PostgreSQL (COPY baseline / {rows_per_record:.1f} rows per record) "
        f"| {pg_records:,.0f} | {pg_records / per_vehicle:,.0f} |"
    )
    return 0


if __name__ == "__main__":
    with contextlib.suppress(KeyboardInterrupt):
        sys.exit(main())
