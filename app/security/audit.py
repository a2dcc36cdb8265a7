"""Audit housekeeping: anonymous refusals counted instead of stored one by one, and retention.

A request without a valid key costs its sender nothing, so each one written as its own audit
row would let anyone grow the table without bound. They are counted in memory per (action,
status) and written as one row per flush (every few seconds): the row's `request` holds the
count and the first and last time, so the log still says that it happened, how much and when.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any

from sqlalchemy import Engine

from eqgw.security import repository as q

# Distinct (action, status) pairs kept between flushes; beyond it they are merged into one.
MAX_KINDS = 256
OTHER = "(other actions)"


@dataclass(slots=True)
class _Count:
    count: int
    first_ts: float
    last_ts: float
    detail: str | None
    vehicle_ids: set[str]


class AnonymousRefusals:
    """Refusals of requests without a valid key, counted until the next flush."""

    def __init__(self) -> None:
        self._counts: dict[tuple[str, int], _Count] = {}

    def add(self, action: str, status: int, detail: str | None, vehicle_id: str | None) -> None:
        """Count one refusal (no I/O)."""
        now = time.time()
        key = (action, status)
        if key not in self._counts and len(self._counts) >= MAX_KINDS:
            key = (OTHER, status)
        c = self._counts.get(key)
        if c is None:
            c = self._counts[key] = _Count(0, now, now, detail, set())
        c.count += 1
        c.last_ts = now
        if vehicle_id is not None and len(c.vehicle_ids) < 10:
            c.vehicle_ids.add(vehicle_id[:64])

    def take(self) -> list[dict[str, Any]]:
        """The audit rows of what was counted since the last call (and forget it)."""
        counts, self._counts = self._counts, {}
        rows = []
        for (action, status), c in counts.items():
            vehicle = next(iter(c.vehicle_ids)) if len(c.vehicle_ids) == 1 else None
            rows.append(
                {
                    "ts": c.last_ts,
                    "key_id": None,
                    "key_name": None,
                    "role": None,
                    "action": action,
                    "vehicle_id": vehicle,
                    "target": None,
                    "request": {
                        "count": c.count,
                        "first_ts": c.first_ts,
                        "last_ts": c.last_ts,
                        "vehicle_ids": sorted(c.vehicle_ids),
                    },
                    "outcome": "refused",
                    "status_code": status,
                    "detail": f"{c.count} request(s) without a valid key: {c.detail}"[:2000],
                    "command_id": None,
                }
            )
        return rows

    def flush(self, engine: Engine) -> int:
        """Write what was counted (blocking: run it in a thread); returns the rows written.
        On failure the counts are put back for the next flush."""
        rows = self.take()
        if not rows:
            return 0
        try:
            with engine.begin() as conn:
                for row in rows:
                    q.add_audit(conn, row)
        except Exception:
            for row in rows:
                r = row["request"]
                key = (row["action"], row["status_code"])
                c = self._counts.setdefault(
                    key, _Count(0, r["first_ts"], r["last_ts"], None, set(r["vehicle_ids"]))
                )
                c.count += r["count"]
                c.first_ts = min(c.first_ts, r["first_ts"])
                c.detail = c.detail or row["detail"]
            raise
        return len(rows)


def prune_audit(engine: Engine, retention_days: float, batch: int = 5000) -> int:
    """Delete audit entries older than `retention_days` (0: keep them all), a batch a
    transaction; returns how many."""
    if retention_days <= 0:
        return 0
    before = time.time() - retention_days * 86400.0
    total = 0
    while True:
        with engine.begin() as conn:
            n = q.prune_audit(conn, before, batch)
        total += n
        if n < batch:
            return total
