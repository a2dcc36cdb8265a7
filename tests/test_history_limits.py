"""A history over more buckets than an answer holds is refused from the count of buckets in
its range, before a row is read, by a real `eqgw serve`: a year of 1 min buckets is not read
(100,001 of them are stored) only to be refused afterwards."""

from __future__ import annotations

import re
import time
from pathlib import Path

import httpx
from sqlalchemy import insert

from eqgw.config import DatabaseSettings
from eqgw.fleet.endpoints import HISTORY_LIMIT
from eqgw.security.keys import create_key
from eqgw.store.engine import create_engine
from eqgw.store.migrate import upgrade_engine
from eqgw.store.models import Rollup, Unit, Vehicle
from tests.proc_helpers import Process, eqgw, free_port, wait_until
from tests.support import web

TOKEN = "history-limits-metrics"
READS = re.compile(r'^eqgw_history_cache_reads_total\{outcome="\w+"\} (\S+)$', re.M)
YEAR = 365 * 86400.0


def _reads(base: str) -> float:
    """Rollup reads the gateway made for history answers (every outcome of its cache)."""
    r = web.get(f"{base}/metrics", headers={"Authorization": f"Bearer {TOKEN}"}, timeout=10)
    return sum(float(n) for n in READS.findall(r.text))


def test_a_year_of_minute_buckets_is_refused_before_it_is_read(db_url: str, tmp_path: Path) -> None:
    now = time.time()
    start = now - YEAR
    # The year of buckets (100,001 rows) is written in one batch, which took over the
    # default 10 s answer deadline on PostgreSQL on a loaded machine; the seeding is not the
    # subject, so it gets all the time it needs.
    engine = create_engine(db_url, deadlines=DatabaseSettings(answer_timeout_s=300))
    try:
        upgrade_engine(engine)
        _, key = create_key(engine, "viewer", "viewer")
        with engine.begin() as conn:
            conn.execute(insert(Vehicle), [{"id": "V1", "name": "V1", "depot": None}])
            unit_id = conn.execute(
                insert(Unit)
                .values(vehicle_id="V1", bus="V1/can0", sa=30, first_seen=start, last_seen=now)
                .returning(Unit.id)
            ).scalar_one()
            first = start - start % 60 + 60
            conn.execute(
                insert(Rollup),
                [
                    {
                        "unit_id": unit_id,
                        "bucket_s": 60,
                        "bucket_ts": first + 60 * i,
                        "v12_n": 1,
                        "v12_sum": 12.5,
                        "v12_min": 12.5,
                        "v12_max": 12.5,
                    }
                    for i in range(HISTORY_LIMIT + 1)
                ],
            )
    finally:
        engine.dispose()
    port = free_port()
    base = f"http://127.0.0.1:{port}"
    proc = Process(
        eqgw("serve"),
        tmp_path,
        {"EQGW_DATABASE_URL": db_url, "EQGW_API_PORT": str(port), "EQGW_API_METRICS_TOKEN": TOKEN},
    )
    auth = {"Authorization": f"Bearer {key}"}

    def history(**params: str) -> httpx.Response:
        return web.get(
            f"{base}/api/v1/vehicles/V1/history", params=params, headers=auth, timeout=60
        )

    try:
        wait_until(lambda: _up(base), 120, "the gateway serving")
        before = _reads(base)
        r = history(**{"from": str(start), "to": str(now), "bucket": "1m", "fields": "v12,v24"})
        assert r.status_code == 422, r.text
        assert _reads(base) == before  # refused without reading a bucket
        body = r.json()
        assert body["type"] == "too_many_points" and body["limit"] == HISTORY_LIMIT
        assert body["buckets"] >= 525_599 and body["fields"] == ["v12", "v24"]
        assert f"more than {HISTORY_LIMIT} 1m buckets" in body["detail"]
        assert "or a wider bucket (15m, 1h, 1d)" in body["detail"]
        # auto is bounded too: past the limit even at 1 d buckets, refused the same way.
        r = history(**{"from": "-1e12", "to": str(now), "bucket": "auto", "fields": "v12"})
        assert r.status_code == 422 and r.json()["type"] == "too_many_points", r.text
        assert "1d buckets" in r.json()["detail"]
        assert _reads(base) == before
        # The same year at 15 min buckets is read (and counted: the counter sees reads).
        r = history(**{"from": str(start), "to": str(now), "bucket": "15m", "fields": "v12"})
        assert r.status_code == 200, r.text
        assert _reads(base) == before + 1
    finally:
        proc.stop()


def _up(base: str) -> bool:
    try:
        return web.get(f"{base}/healthz", timeout=5).status_code == 200
    except httpx.HTTPError:
        return False
