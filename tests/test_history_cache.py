"""The history cache: what it serves equals what the database holds, on SQLite and PostgreSQL,
whatever was written, where and when, after a span was cached."""

from __future__ import annotations

import random
import re
import time
from typing import Any

from sqlalchemy import Engine

from eqgw.store import queries
from eqgw.store.history_cache import HistoryCache
from eqgw.store.retention import DAY_S, prune
from eqgw.store.writes import Batch, load_unit_ids, write_batch
from tests.api_helpers import served, wait_for

UNIT = ("V1/can0", 30)
T0 = 1_700_000_000.0 - 1_700_000_000.0 % 86400  # midnight, so every width aligns
METRICS = ["v12", "v24"]


class Clock:
    def __init__(self, now: float) -> None:
        self.now = now

    def __call__(self) -> float:
        return self.now


def _write(
    engine: Engine,
    rows: list[dict[str, Any]],
    key: tuple[str, int] = UNIT,
    vehicle: str = "V1",
) -> None:
    b = Batch()
    b.vehicles[vehicle] = {"id": vehicle, "name": vehicle, "depot": "D"}
    b.units[key] = vehicle
    b.measurements = [(key, r) for r in rows]
    # SQLite: the write lock at BEGIN, as the gateway's writer takes it (it may be running).
    with engine.execution_options(sqlite_begin="IMMEDIATE").begin() as conn:
        write_batch(conn, b, load_unit_ids(conn))


def _samples(start: float, end: float, step: float, seed: int) -> list[dict[str, Any]]:
    rng = random.Random(seed)
    out = []
    ts = start
    while ts < end:
        out.append(
            {
                "ts": ts,
                "v12": rng.uniform(11, 15),
                "v24": rng.uniform(22, 29),
                "i12": 1.0,
                "i24": 2.0,
            }
        )
        ts += step
    return out


def _uid(engine: Engine) -> int:
    with engine.connect() as conn:
        uid = queries.unit_id_of(conn, *UNIT)
    assert uid is not None
    return uid


def _both(
    engine: Engine, cache: HistoryCache, start: float, end: float, width: int = 60
) -> dict[str, list[dict[str, Any]]]:
    """The cache's answer, checked against a plain read of the database in the same breath."""
    uid = _uid(engine)
    with engine.begin() as conn:
        got = cache.series(conn, uid, METRICS, start, end, width)
        want = queries.read_rollups(conn, uid, METRICS, width, start, end)
    assert got == want
    return got


def test_cached_reads_equal_database_reads_over_random_ranges(engine: Engine) -> None:
    _write(engine, _samples(T0, T0 + 6 * 3600, 7.0, seed=1))
    clock = Clock(T0 + 6 * 3600 + 30)
    cache = HistoryCache(clock=clock, seal_s=120)
    rng = random.Random(2)
    for _ in range(60):
        width = rng.choice([60, 60, 60, 900, 3600])
        start = T0 + rng.uniform(-3600, 5 * 3600)
        end = start + rng.choice([600, 3600, 6 * 3600, 86400])
        _both(engine, cache, start, end, width)
        clock.now += rng.choice([0, 1, 30, 400])
    assert cache.stats.hits > 20  # most ranges after the first were served from spans
    assert cache.stats.misses > 0


def test_a_late_write_into_a_sealed_bucket_is_seen(engine: Engine) -> None:
    _write(engine, _samples(T0, T0 + 3 * 3600, 5.0, seed=3))
    clock = Clock(T0 + 3 * 3600)
    cache = HistoryCache(clock=clock)
    start, end = T0, T0 + 3 * 3600
    first = _both(engine, cache, start, end)
    assert _both(engine, cache, start, end) == first
    assert cache.stats.hits == 1

    # A late sample merged into an hour-old bucket (a replay, a forwarder catching up, another
    # gateway): one more sample, a new minimum.
    _write(engine, [{"ts": T0 + 3600 + 1.5, "v12": 0.25, "v24": 30.0, "i12": 0.0, "i24": 0.0}])
    after = _both(engine, cache, start, end)
    assert after != first
    bucket = next(p for p in after["v12"] if p["ts"] == T0 + 3600)
    assert bucket["min"] == 0.25 and bucket["count"] == 13
    assert cache.stats.stale >= 1

    # A bucket where there was none (a gap filled later).
    _write(engine, [{"ts": T0 - 60.0, "v12": 12.0, "v24": 24.0, "i12": 0.0, "i24": 0.0}])
    gap = _both(engine, cache, T0 - 3600, end)
    assert gap["v12"][0]["ts"] == T0 - 60.0
    # ... and inside a cached span's range.
    _write(engine, _samples(T0 + 3 * 3600 - 600, T0 + 3 * 3600, 30.0, seed=4))
    _both(engine, cache, start, end)


def test_retention_deleting_cached_buckets_is_seen(engine: Engine) -> None:
    _write(engine, _samples(T0, T0 + 4 * 3600, 10.0, seed=5))
    clock = Clock(T0 + 4 * 3600)
    cache = HistoryCache(clock=clock)
    start, end = T0, T0 + 4 * 3600
    before = _both(engine, cache, start, end)
    # Rollups older than T0 + 2 h go.
    prune(engine, raw_days=1000, rollup_days=(clock.now - (T0 + 2 * 3600)) / DAY_S, now=clock.now)
    after = _both(engine, cache, start, end)
    assert len(after["v12"]) == len(before["v12"]) - 120
    assert after["v12"][0]["ts"] == T0 + 2 * 3600


def test_a_bucket_deleted_and_made_again_with_as_many_samples_is_seen(engine: Engine) -> None:
    def row(ts: float, v12: float) -> dict[str, Any]:
        return {"ts": ts, "v12": v12, "v24": 24.0, "i12": 0.0, "i24": 0.0}

    _write(engine, [row(T0 + 60 * i + 5, 12.0) for i in range(10)])  # a sample a minute
    clock = Clock(T0 + 3600)
    cache = HistoryCache(clock=clock)
    start, end = T0, T0 + 600
    assert _both(engine, cache, start, end)["v12"][0]["max"] == 12.0
    # The retention drops the first minute's bucket, then a late frame (a forwarder
    # catching up) makes it again: as many buckets and samples as before, another value.
    prune(engine, raw_days=1000, rollup_days=(clock.now - (T0 + 60)) / DAY_S, now=clock.now)
    _write(engine, [row(T0 + 30, 99.0)])
    got = _both(engine, cache, start, end)
    assert got["v12"][0] == {"ts": T0, "count": 1, "min": 99.0, "max": 99.0, "avg": 99.0}
    assert cache.stats.stale == 1
    # A deletion of another unit's rollups leaves this unit's spans alone.
    other = ("V2/can0", 30)
    _write(engine, [row(T0 - 3600, 1.0)], key=other, vehicle="V2")
    prune(engine, raw_days=1000, rollup_days=(clock.now - (T0 - 60)) / DAY_S, now=clock.now)
    _both(engine, cache, start, end)
    assert cache.stats.stale == 1 and cache.stats.hits == 1


def test_the_newest_buckets_are_read_every_time(engine: Engine) -> None:
    now = T0 + 2 * 3600
    _write(engine, _samples(T0, now, 1.0, seed=6))
    clock = Clock(now + 0.5)
    cache = HistoryCache(clock=clock, seal_s=120)
    _both(engine, cache, T0, now + 60)
    # The bucket still filling, and one inside the seal: neither is kept, both are fresh.
    _write(engine, _samples(now, now + 0.5, 0.25, seed=7))
    _write(engine, [{"ts": now - 90.0 + 0.5, "v12": 99.0, "v24": 99.0, "i12": 0.0, "i24": 0.0}])
    got = _both(engine, cache, T0, now + 60)
    assert got["v12"][-1]["ts"] == now and got["v12"][-1]["count"] == 2
    assert max(p["max"] for p in got["v12"]) == 99.0
    assert cache.stats.stale == 0  # the sealed span itself was untouched


def test_a_rolling_window_extends_its_span_and_stays_bounded(engine: Engine) -> None:
    _write(engine, _samples(T0, T0 + 8 * 3600, 15.0, seed=8))
    clock = Clock(T0 + 3600)
    cache = HistoryCache(clock=clock, extend_after=5, max_age_s=1e9)
    while clock.now < T0 + 8 * 3600:
        _both(engine, cache, clock.now - 3600, clock.now)
        clock.now += 61.0
    # The window moved seven hours; its spans keep at most about two windows of buckets.
    assert cache.size <= 2 * len(METRICS) * 125
    assert cache.stats.hits > 5 * cache.stats.misses


def test_spans_are_read_again_when_too_old(engine: Engine) -> None:
    _write(engine, _samples(T0, T0 + 3600, 10.0, seed=9))
    clock = Clock(T0 + 3600)
    cache = HistoryCache(clock=clock, max_age_s=600)
    _both(engine, cache, T0, T0 + 3600)
    clock.now += 601
    _both(engine, cache, T0, T0 + 3600)
    assert (cache.stats.stale, cache.stats.hits, cache.stats.misses) == (1, 0, 1)


def test_the_cache_holds_at_most_max_buckets(engine: Engine) -> None:
    _write(engine, _samples(T0, T0 + 6 * 3600, 30.0, seed=10))
    clock = Clock(T0 + 7 * 3600)  # every bucket sealed
    cache = HistoryCache(clock=clock, max_buckets=200)
    _both(engine, cache, T0, T0 + 3600, 60)  # 2 series x 60 buckets
    _both(engine, cache, T0, T0 + 6 * 3600, 900)  # 2 x 24
    _both(engine, cache, T0, T0 + 6 * 3600, 3600)  # 2 x 6: 180 held
    assert cache.size == 180 and cache.stats.evicted == 0
    _both(engine, cache, T0, T0 + 1.5 * 3600, 60)  # 2 x 90 replace 2 x 60: 240 > 200
    assert cache.size == 192 and cache.stats.evicted == 2  # the 900 s series went
    # A range bigger than the whole cache is served, just not kept.
    _both(engine, cache, T0, T0 + 6 * 3600, 60)
    assert cache.size <= 200
    # max_buckets 0: no cache at all.
    off = HistoryCache(clock=clock, max_buckets=0)
    _both(engine, off, T0, T0 + 6 * 3600)
    assert off.size == 0 and off.stats.misses == 0


async def test_history_endpoint_serves_from_the_cache_and_sees_late_writes(db_url: str) -> None:
    async with served(db_url, vehicles=1) as s:
        c = s.client
        live = (await c.get("/api/v1/vehicles/SIM-001/live", headers=s.auth())).json()
        key = (live["units"][0]["bus"], live["units"][0]["unit"])
        now = time.time()
        old = now - now % 60 - 3 * 3600
        rows = _samples(old, old + 2 * 3600, 10.0, seed=11)
        _write(s.rt.engine, rows, key=key, vehicle="SIM-001")
        url = f"/api/v1/vehicles/SIM-001/history?from={old}&to={now}&bucket=1m&fields=v12,v24"

        async def stored() -> Any:
            r = await c.get(url, headers=s.auth())  # once the unit index knows the unit
            return r.status_code == 200 and r.json()["series"]

        first = await wait_for(stored, what="the unit in the index")
        assert len(first["v12"]) >= 120
        assert (await c.get(url, headers=s.auth())).json()["series"]["v12"][:120] == first["v12"][
            :120
        ]
        late = {"ts": old + 600.5, "v12": 0.125, "v24": 24.0, "i12": 0.0, "i24": 0.0}
        _write(s.rt.engine, [late], key=key, vehicle="SIM-001")
        after = (await c.get(url, headers=s.auth())).json()["series"]["v12"]
        bucket = next(p for p in after if p["ts"] == old + 600)
        assert bucket["min"] == 0.125 and bucket["count"] == 7
        m = (await c.get("/metrics", headers=s.auth())).text
        hits = re.search(r'^eqgw_history_cache_reads_total\{outcome="hit"\} (\S+)$', m, re.M)
        stale = re.search(r'^eqgw_history_cache_reads_total\{outcome="stale"\} (\S+)$', m, re.M)
        assert hits is not None and float(hits.group(1)) >= 1
        assert stale is not None and float(stale.group(1)) >= 1
        assert re.search(r"^eqgw_history_cache_buckets \d", m, re.M)
