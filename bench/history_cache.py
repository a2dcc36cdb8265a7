"""History cache benchmark: what a 24 h history at 1 min costs from the database and from the
cache, what the check on every use costs, and how much memory a cached bucket takes.

Usage: python -m bench.history_cache [--url URL] [--rounds 40]

Seeds 24 h of 1 s measurements for one unit (bench.api.seed, the store's write path) into a
fresh SQLite file, or into URL (a PostgreSQL database the bench may write to), then times, in
this process, with the same connection kind the API uses (`engine.begin()`), median and p90 of
`--rounds` reads of two fields (v12, v24) over the last 24 h:
- the plain read (`queries.read_rollups`, what the API does with the cache off);
- a miss (a new, empty cache: the read plus keeping the span);
- a hit (the check, the fresh tail read, the cached points sliced);
- the check alone (`rollup_fingerprints` + `rollup_generation` of the cached range).
Memory: tracemalloc's growth while a cache holds the unit's spans at 1 min, per bucket held.
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
import tracemalloc
from collections.abc import Callable
from pathlib import Path
from typing import Any

from sqlalchemy import Engine

from bench.api import DAY_S, seed
from eqgw.store import queries
from eqgw.store.engine import create_engine
from eqgw.store.history_cache import HistoryCache

FIELDS = ["v12", "v24"]
WIDTH = 60


def _times(engine: Engine, rounds: int, fn: Callable[[Any], object]) -> list[float]:
    out = []
    for _ in range(rounds):
        with engine.begin() as conn:
            t0 = time.perf_counter()
            fn(conn)
            out.append((time.perf_counter() - t0) * 1000)
    return out


def _row(name: str, ms: list[float]) -> str:
    p90 = sorted(ms)[int(0.9 * (len(ms) - 1))]
    return f"  {name:<34} median {statistics.median(ms):7.2f} ms   p90 {p90:7.2f} ms"


def run(url: str, rounds: int) -> None:
    now = time.time()
    rows = seed(url, ["BENCH-1"], now)
    engine = create_engine(url)
    try:
        with engine.connect() as conn:
            uid = queries.unit_id_of(conn, "BENCH-1/sim", 30)
        assert uid is not None
        start, end = now - DAY_S, now
        print(f"{engine.dialect.name}: {rows} measurements seeded (24 h at 1 s, one unit); "
              f"{rounds} reads of {', '.join(FIELDS)} over 24 h at 1 min each")  # fmt: skip
        plain = _times(
            engine, rounds, lambda c: queries.read_rollups(c, uid, FIELDS, WIDTH, start, end)
        )
        print(_row("database read (no cache)", plain))
        miss = _times(
            engine, rounds, lambda c: HistoryCache().series(c, uid, FIELDS, start, end, WIDTH)
        )
        print(_row("cache miss (read and keep)", miss))
        cache = HistoryCache()
        with engine.begin() as conn:
            cache.series(conn, uid, FIELDS, start, end, WIDTH)
        hit = _times(engine, rounds, lambda c: cache.series(c, uid, FIELDS, start, end, WIDTH))
        print(_row("cache hit (check, tail, slice)", hit))
        sealed = min(end, (now - cache.seal_s) // WIDTH * WIDTH)

        def check(conn: Any) -> None:
            queries.rollup_fingerprints(conn, uid, FIELDS, WIDTH, start, sealed)
            queries.rollup_generation(conn, uid)

        print(_row("the check alone", _times(engine, rounds, check)))
        print(f"  hits {cache.stats.hits}, misses {cache.stats.misses}, stale {cache.stats.stale}")
        tracemalloc.start()
        before = tracemalloc.get_traced_memory()[0]
        held = HistoryCache()
        with engine.begin() as conn:
            held.series(conn, uid, FIELDS, start, end, WIDTH)
        grown = tracemalloc.get_traced_memory()[0] - before
        tracemalloc.stop()
        print(f"  memory: {held.size} buckets held, {grown / 1e3:.0f} kB, "
              f"{grown / max(held.size, 1):.0f} bytes per bucket")  # fmt: skip
    finally:
        engine.dispose()


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0] if __doc__ else None)
    p.add_argument("--url", help="database URL (default: a fresh SQLite file)")
    p.add_argument("--rounds", type=int, default=40)
    args = p.parse_args()
    if args.url:
        run(args.url, args.rounds)
        return 0
    with tempfile.TemporaryDirectory(prefix="eqgw-bench-cache-") as tmp:
        run(f"sqlite:///{Path(tmp) / 'eqgw.db'}", args.rounds)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
