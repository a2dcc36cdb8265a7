"""The running gateway as routes reach it: `Runtime` (`rt: Rt`), built by the lifespan.

It sits below the domains: the services it carries (commands, keys, the write limit, the
audit log) are the domains' own, named here for their types only and handed in by
`eqgw.api.lifespan.runtime`.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Awaitable, Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Annotated, Any, Concatenate, Unpack

from fastapi import Depends, Request
from sqlalchemy import Connection, Engine

from eqgw.config import Settings
from eqgw.store.engine import (
    database_deadline_scope,
    health_of,
    restart_deadline,
    unavailable_error,
)
from eqgw.store.history_cache import HistoryCache
from eqgw.store.transaction import P, R, run_in_transaction
from eqgw.web.errors import ApiError
from eqgw.web.settings import ApiSettings

if TYPE_CHECKING:
    from eqgw.commands.service import CommandService
    from eqgw.ingest.service import IngestService
    from eqgw.security.audit import AuditFields, AuditLog
    from eqgw.security.keys import KeyAuthenticator, Principal
    from eqgw.security.limits import RateLimiter


@dataclass
class Runtime:
    """Everything the lifespan opened, for the routers (reached through `app.state.rt`)."""

    settings: Settings
    api: ApiSettings
    engine: Engine
    ingest: IngestService
    commands: CommandService
    keys: KeyAuthenticator
    limiter: RateLimiter
    audit_log: AuditLog
    fleet: Any = None
    history: HistoryCache = field(default_factory=HistoryCache)
    # Follows the fleet in the database (eqgw.fleet.sync.FleetSync); set by the lifespan.
    fleet_sync: Any = None
    started_at: float = field(default_factory=time.time)
    _cache: dict[str, tuple[float, Any]] = field(default_factory=dict)
    _loading: dict[str, asyncio.Future[Any]] = field(default_factory=dict)

    def fleet_changed(self) -> None:
        """The fleet's vehicles or buses changed: listings rendered before are not reused."""
        self._cache.clear()

    async def db(
        self, fn: Callable[Concatenate[Connection, P], R], /, *args: P.args, **kwargs: P.kwargs
    ) -> R:
        """Run a store query in a worker thread, in one transaction, within the request's
        database deadline; a database that failed moments ago is not asked (503 at once)."""
        if health_of(self.engine).down():
            raise unavailable_error()
        return await run_in_transaction(self.engine, fn, *args, **kwargs)

    async def db_page(
        self, fn: Callable[Concatenate[Connection, P], R], /, *args: P.args, **kwargs: P.kwargs
    ) -> R:
        """`db` for one page of a streamed answer (an export): the page's database work
        ends within the request's deadline counted from now. A stream lasts as long as its
        range and its client take, so the request's deadline, counted from its start, would
        cut a long export part-way; a database that stops answering still ends it within
        one deadline."""
        with database_deadline_scope():
            restart_deadline(self.api.db_deadline_s)
            return await self.db(fn, *args, **kwargs)

    async def cached(
        self,
        name: str,
        ttl: float,
        load: Callable[[], Awaitable[Any]],
        *,
        stale_while_loading: bool = False,
        max_stale_s: float | None = None,
    ) -> Any:
        """The value of `load()`, reused for `ttl` seconds.

        Single flight: requests that miss while a load runs wait for that load instead of
        starting their own, so an expired entry under 50 concurrent clients costs one load.
        With `stale_while_loading` (and a `ttl` above 0, which means always fresh), an
        expired value is returned at once while one load refreshes it in the background:
        only the very first request waits for a load. With `max_stale_s`, only a value that
        expired at most that long ago is: after a quiet spell the next request waits for a
        fresh one instead of getting whatever the last request before it left.
        """
        hit = self._cache.get(name)
        now = time.monotonic()
        if hit is not None and hit[0] > now:
            return hit[1]
        if hit is not None and max_stale_s is not None and now - hit[0] > max_stale_s:
            hit = None
        pending = self._loading.get(name)
        if pending is None:
            pending = asyncio.ensure_future(load())
            self._loading[name] = pending

            def done(fut: asyncio.Future[Any]) -> None:
                self._loading.pop(name, None)
                if not fut.cancelled() and fut.exception() is None:
                    self._cache[name] = (time.monotonic() + ttl, fut.result())

            pending.add_done_callback(done)
        if hit is not None and stale_while_loading and ttl > 0:
            return hit[1]
        # Shielded: one waiter cancelled (a client gone) does not cancel the others' load.
        return await asyncio.shield(pending)

    async def check_write_rate(
        self,
        who: Principal,
        action: str,
        *,
        vehicle_id: str | None = None,
        target: str | None = None,
        request: dict[str, Any] | None = None,
    ) -> None:
        """Count a write against the key's limit; past it, audit the refusal and raise a 429
        with Retry-After. Every write endpoint (commands, keys, alerts, webhooks) calls this."""
        wait = await self.limiter.retry_after(who.key_id)
        if wait is None:
            return
        detail = f"too many writes from this key; retry in {wait:.0f} s"
        await self.audit(
            who,
            action,
            outcome="refused",
            status=429,
            detail=detail,
            vehicle_id=vehicle_id,
            target=target,
            request=request,
        )
        raise ApiError(429, detail, headers={"Retry-After": str(max(1, round(wait)))})

    async def audit(
        self,
        who: Principal | None,
        action: str,
        **fields: Unpack[AuditFields],
    ) -> None:
        """Append to the audit log (`eqgw.security.audit.AuditLog.append`: what is stored,
        and how a refusal without a valid key is counted instead)."""
        await self.audit_log.append(self.db, who, action, **fields)


def runtime_of(request: Request) -> Runtime:
    """The running gateway."""
    rt: Runtime = request.app.state.rt
    return rt


async def get_rt(request: Request) -> Runtime:
    """The running gateway, as a dependency (a coroutine: FastAPI runs a plain function
    dependency in its thread pool, a thread hop on every request)."""
    return runtime_of(request)


# The running gateway, as a route's parameter (`rt: Rt`).
Rt = Annotated[Runtime, Depends(get_rt)]
