"""What a history request past the point limit costs the gateway: a year of 1 min buckets.

Usage: python -m bench.history_refusal [--days 365]

Stores `--days` of 1 min rollups of v12 and v24 for one unit in a fresh SQLite file, starts
`eqgw serve` on it and, after one small request (the process's first loads the fleet), asks
`history?bucket=1m` over the whole range twice (refused: more than 100,000 buckets per field),
then the same range at 15 min buckets (answered: none stored at that width). Prints the time
of each answer and the gateway's resident memory (VmRSS) before and after each.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import httpx
from sqlalchemy import insert

from eqgw.security.keys import create_key
from eqgw.store.engine import create_engine
from eqgw.store.migrate import upgrade_engine
from eqgw.store.models import Rollup, Unit, Vehicle, rollup_columns
from tests.proc_helpers import Process, eqgw, free_port, wait_until


def _rss_kb(pid: int) -> int:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1])
    return 0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--days", type=int, default=365)
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        url = f"sqlite:///{tmp}/db.sqlite"
        now = time.time()
        start = now - args.days * 86400.0
        engine = create_engine(url)
        upgrade_engine(engine)
        _, key = create_key(engine, "bench", "viewer")
        first = start - start % 60 + 60
        n = int((now - first) // 60)
        with engine.begin() as conn:
            conn.execute(insert(Vehicle), [{"id": "V1", "name": "V1", "depot": None}])
            unit = conn.execute(
                insert(Unit).values(vehicle_id="V1", bus="V1/can0", sa=30).returning(Unit.id)
            ).scalar_one()
            values = {
                c: v
                for metric in ("v12", "v24")
                for c, v in zip(rollup_columns(metric), (20, 250.0, 12.4, 12.6), strict=True)
            }
            for lo in range(0, n, 50_000):
                conn.execute(
                    insert(Rollup),
                    [
                        {"unit_id": unit, "bucket_s": 60, "bucket_ts": first + 60 * i, **values}
                        for i in range(lo, min(n, lo + 50_000))
                    ],
                )
        engine.dispose()
        print(f"{n:,} 1 min buckets per field stored ({args.days} days, v12 and v24)")
        port = free_port()
        base = f"http://127.0.0.1:{port}"
        proc = Process(
            eqgw("serve"), Path(tmp), {"EQGW_DATABASE_URL": url, "EQGW_API_PORT": str(port)}
        )
        try:

            def up() -> bool:
                try:
                    return httpx.get(f"{base}/healthz", timeout=5).status_code == 200
                except httpx.HTTPError:
                    return False

            wait_until(up, 120, "the gateway")
            # Warm: the first request of a process loads the fleet and the key's scope.
            httpx.get(
                f"{base}/api/v1/vehicles/V1/history",
                params={"from": str(now - 3600), "to": str(now), "bucket": "1m"},
                headers={"Authorization": f"Bearer {key}"},
                timeout=60,
            )
            for bucket in ("1m", "1m", "15m"):
                before = _rss_kb(proc.proc.pid)
                t0 = time.perf_counter()
                r = httpx.get(
                    f"{base}/api/v1/vehicles/V1/history",
                    params={"from": str(start), "to": str(now), "bucket": bucket,
                            "fields": "v12,v24"},
                    headers={"Authorization": f"Bearer {key}"},
                    timeout=300,
                )  # fmt: skip
                took = time.perf_counter() - t0
                after = _rss_kb(proc.proc.pid)
                print(
                    f"bucket={bucket}: HTTP {r.status_code} in {took * 1000:.0f} ms, "
                    f"{len(r.content):,} bytes; gateway RSS {before / 1024:.0f} -> "
                    f"{after / 1024:.0f} MB (+{(after - before) / 1024:.1f} MB)"
                )
        finally:
            proc.stop()


if __name__ == "__main__":
    main()
