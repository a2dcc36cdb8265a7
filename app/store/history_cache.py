"""A cache of sealed rollup buckets for history reads, checked against the database on use.

A 24 h history at 1 min buckets is thousands of rows, and reading them (a Python object per
value) is most of what the request costs, every time, although all but the last few minutes
of it are the same as a second ago. This cache keeps, per (unit, metric, width), a span of
buckets that had ended at least `seal_s` before they were read, as the points
`queries.read_rollups` makes.

Nothing is trusted without a check. Every use first asks the database for the fingerprint of
the cached part of the range (`queries.rollup_fingerprints`: buckets, samples, first and last
bucket start, aggregated by the database, no row per bucket reaching Python) and compares it
with the same figures of the cached points. Rollups change only by a merge, which adds at
least one sample to a bucket (so the samples grow), by a new bucket (the buckets grow), or by
the retention deleting a unit's oldest buckets. A deletion alone changes the fingerprint too,
but a deletion followed by a late frame that makes the same bucket again with as many samples
would not: so the retention also bumps the unit's deletion generation in the deleting
transaction (`rollup_deletions`), and a span read before a deletion is read again. That
covers late frames, a replay or a forwarder catching up into the past, another process or
gateway writing the same database, and the retention. A span is also read again once it is
`max_age_s` old. The buckets after the sealed horizon (the last `seal_s` and the bucket
still filling) are read from the database on every request.

Shared by the API's worker threads: spans are immutable and swapped under a lock; the cache
holds at most `max_buckets` points, least recently used spans going first.
"""

from __future__ import annotations

import math
import threading
import time
from bisect import bisect_left
from collections import OrderedDict
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from itertools import accumulate

from sqlalchemy import Connection

from eqgw.store import queries

Point = queries.Bucket
SpanKey = tuple[int, str, int]  # (unit id, metric, width in s)


@dataclass(frozen=True)
class _Span:
    """The buckets of one series with starts in [start, end), read at `read_at`."""

    start: float
    end: float
    points: list[Point]
    ts: list[float]  # bucket starts, for bisect
    samples: list[int]  # samples[i] = sum of the counts of points[:i]
    read_at: float
    generation: int  # the unit's rollup deletion generation, read before the points

    @classmethod
    def of(
        cls, start: float, end: float, points: list[Point], read_at: float, generation: int
    ) -> _Span:
        return cls(
            start,
            end,
            points,
            [p["ts"] for p in points],
            list(accumulate((p["count"] for p in points), initial=0)),
            read_at,
            generation,
        )

    def bounds(self, start: float, end: float) -> tuple[int, int]:
        return bisect_left(self.ts, start), bisect_left(self.ts, end)

    def fingerprint(self, start: float, end: float) -> queries.Fingerprint:
        i, j = self.bounds(start, end)
        if i == j:
            return (0, 0, None, None)
        return (j - i, self.samples[j] - self.samples[i], self.ts[i], self.ts[j - 1])


@dataclass
class CacheStats:
    """Reads by outcome (each read is one of hits, misses, stale), and evictions."""

    hits: int = 0  # served from checked spans (plus the newest buckets from the database)
    misses: int = 0  # found no span covering the range's start: read from the database
    stale: int = 0  # found a span changed in the database, or too old: read again
    evicted: int = 0  # spans dropped for room


@dataclass
class HistoryCache:
    max_buckets: int = 200_000
    seal_s: float = 120.0
    max_age_s: float = 600.0
    # Extend a span once this many sealed buckets lie past its end (read each time till then).
    extend_after: int = 10
    clock: Callable[[], float] = time.time
    stats: CacheStats = field(default_factory=CacheStats)
    _spans: OrderedDict[SpanKey, _Span] = field(default_factory=OrderedDict)
    _size: int = 0
    _lock: threading.Lock = field(default_factory=threading.Lock)

    @property
    def size(self) -> int:
        """Points held."""
        return self._size

    def series(
        self,
        conn: Connection,
        unit_id: int,
        metrics: Sequence[str],
        start: float,
        end: float,
        width: int,
    ) -> dict[str, list[Point]]:
        """What `queries.read_rollups(conn, unit_id, metrics, width, start, end)` returns."""
        now = self.clock()
        sealed = min(end, math.floor((now - self.seal_s) / width) * width)
        if not sealed > start or self.max_buckets <= 0:
            return queries.read_rollups(conn, unit_id, metrics, width, start, end)
        with self._lock:
            found = {m: self._spans.get((unit_id, m, width)) for m in metrics}
            for m, span in found.items():
                if span is not None:
                    self._spans.move_to_end((unit_id, m, width))
        spans = {
            m: span
            for m, span in found.items()
            if span is not None and span.start <= start < span.end
        }
        if len(spans) < len(metrics):
            self._count("misses")
            return self._read(conn, unit_id, metrics, start, end, width, sealed, now, {})
        if any(now - span.read_at > self.max_age_s for span in spans.values()):
            self._count("stale")
            return self._read(conn, unit_id, metrics, start, end, width, sealed, now, {})
        upto = min(sealed, *(s.end for s in spans.values()))
        db = queries.rollup_fingerprints(conn, unit_id, metrics, width, start, upto)
        # The deletion generation is read after the fingerprints: a deletion that a bucket
        # written again since hides from them (same buckets, same samples) committed before
        # them, so this later statement sees its generation even under READ COMMITTED.
        generation = queries.rollup_generation(conn, unit_id)
        if any(spans[m].fingerprint(start, upto) != db[m] for m in metrics) or any(
            span.generation != generation for span in spans.values()
        ):
            self._count("stale")
            return self._read(conn, unit_id, metrics, start, end, width, sealed, now, {})
        self._count("hits")
        if sealed - upto >= self.extend_after * width:
            return self._read(conn, unit_id, metrics, start, end, width, sealed, now, spans)
        tail = queries.read_rollups(conn, unit_id, metrics, width, upto, end)
        out: dict[str, list[Point]] = {}
        for m in metrics:
            span = spans[m]
            i, j = span.bounds(start, upto)
            out[m] = span.points[i:j] + tail[m]
        return out

    def _read(
        self,
        conn: Connection,
        unit_id: int,
        metrics: Sequence[str],
        start: float,
        end: float,
        width: int,
        sealed: float,
        now: float,
        checked: dict[str, _Span],
    ) -> dict[str, list[Point]]:
        """Read what `checked` (spans just found unchanged up to their end, or none) lacks,
        keep the sealed part as new spans and return the range."""
        # Read before the points: a deletion after it makes the new spans stale at their
        # next use, one before it is in the points already.
        generation = queries.rollup_generation(conn, unit_id)
        if any(span.generation != generation for span in checked.values()):
            checked = {}  # a deletion since the check: nothing held is reused
        frm = min((s.end for s in checked.values()), default=start)
        fresh = queries.read_rollups(conn, unit_id, metrics, width, frm, end)
        out: dict[str, list[Point]] = {}
        new: dict[SpanKey, _Span] = {}
        for m in metrics:
            span = checked.get(m)
            points = fresh[m]
            cut = bisect_left(points, sealed, key=lambda p: p["ts"])
            if span is None:
                keep_from, head = start, []
            else:
                # A span keeps at most one range's length before the range asked for, so
                # a rolling window does not grow it without end.
                keep_from = max(span.start, start - (end - start))
                i, j = span.bounds(keep_from, frm)
                head = span.points[i:j]
            sealed_points = head + points[:cut]
            read_at = now if span is None else min(now, span.read_at)
            new[(unit_id, m, width)] = _Span.of(
                keep_from, sealed, sealed_points, read_at, generation
            )
            i = bisect_left(sealed_points, start, key=lambda p: p["ts"])
            out[m] = sealed_points[i:] + points[cut:]
        self._store(new)
        return out

    def _store(self, spans: dict[SpanKey, _Span]) -> None:
        with self._lock:
            for key, span in spans.items():
                old = self._spans.pop(key, None)
                if old is not None:
                    self._size -= len(old.points)
                if len(span.points) > self.max_buckets:
                    continue
                self._spans[key] = span
                self._size += len(span.points)
            while self._size > self.max_buckets and self._spans:
                _, gone = self._spans.popitem(last=False)
                self._size -= len(gone.points)
                self.stats.evicted += 1

    def _count(self, what: str) -> None:
        with self._lock:
            setattr(self.stats, what, getattr(self.stats, what) + 1)

    def clear(self) -> None:
        with self._lock:
            self._spans.clear()
            self._size = 0
