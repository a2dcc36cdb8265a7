"""The write rate limit: writes per key in a sliding window, one budget per key across every
gateway and process of one database (`Runtime.check_write_rate` asks it)."""

from __future__ import annotations

import asyncio

from sqlalchemy import Engine

from eqgw.security import limit_repository as limit_queries


class RateLimiter:
    """Sliding-window limit of writes per key, kept in the database (`limit_repository`):
    one budget per key across every gateway and process of one database."""

    def __init__(self, limit: int, window_s: float, engine: Engine) -> None:
        self.limit = limit
        self.window_s = window_s
        # SQLite: the write lock from the transaction's start, waited for up to busy_timeout
        # (a deferred transaction upgrading later would fail at once under another writer).
        self._engine = engine.execution_options(sqlite_begin="IMMEDIATE")

    def _charge(self, key_id: int) -> float | None:
        with self._engine.begin() as conn:
            return limit_queries.charge_write(conn, key_id, self.limit, self.window_s)

    async def retry_after(self, key_id: int) -> float | None:
        """Record a write; None if allowed, else seconds until the next one is. Raises the
        database's error when it cannot be asked (the route answers 503: no write is let
        through uncounted, and the write itself would need the database anyway)."""
        return await asyncio.to_thread(self._charge, key_id)
