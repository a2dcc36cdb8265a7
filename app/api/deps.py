"""What routers share: the running gateway (`Runtime`), key checks by role, audit, rate limits."""

from __future__ import annotations

import asyncio
import math
import time
from collections import deque
from collections.abc import Awaitable, Callable
from dataclasses import dataclass, field
from typing import Any

from fastapi import Depends, Request
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer
from sqlalchemy import Engine

from app.api.auth import KeyAuthenticator, Principal
from app.api.errors import ApiError
from app.api.settings import ApiSettings
from app.commands.service import CommandService
from app.config import Settings
from app.ingest.service import IngestService
from app.store import api_queries as q
from app.store.history_cache import HistoryCache


class RateLimiter:
    """Sliding-window limit of writes per key."""

    def __init__(self, limit: int, window_s: float) -> None:
        self.limit = limit
        self.window_s = window_s
        self._hits: dict[int, deque[float]] = {}

    def retry_after(self, key_id: int) -> float | None:
        """Record a write; None if allowed, else seconds until the next one is."""
        now = time.monotonic()
        hits = self._hits.setdefault(key_id, deque())
        while hits and hits[0] <= now - self.window_s:
            hits.popleft()
        if len(hits) >= self.limit:
            return hits[0] + self.window_s - now
        hits.append(now)
        return None


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
    fleet: Any = None
    history: HistoryCache = field(default_factory=HistoryCache)
    started_at: float = field(default_factory=time.time)
    _cache: dict[str, tuple[float, Any]] = field(default_factory=dict)
    _loading: dict[str, asyncio.Future[Any]] = field(default_factory=dict)

    async def db(self, fn: Callable[..., Any], *args: Any, **kwargs: Any) -> Any:
        """Run a store query in a worker thread, in one transaction."""

        def run() -> Any:
            with self.engine.begin() as conn:
                return fn(conn, *args, **kwargs)

        return await asyncio.to_thread(run)

    async def cached(
        self,
        name: str,
        ttl: float,
        load: Callable[[], Awaitable[Any]],
        *,
        stale_while_loading: bool = False,
    ) -> Any:
        """The value of `load()`, reused for `ttl` seconds.

        Single flight: requests that miss while a load runs wait for that load instead of
        starting their own, so an expired entry under 50 concurrent clients costs one load.
        With `stale_while_loading` (and a `ttl` above 0, which means always fresh), an
        expired value is returned at once while one load refreshes it in the background:
        only the very first request waits for a load.
        """
        hit = self._cache.get(name)
        now = time.monotonic()
        if hit is not None and hit[0] > now:
            return hit[1]
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
        wait = self.limiter.retry_after(who.key_id)
        if wait is None:
            return
        detail = f"too many writes from this key; retry in {wait:.0f} s"
        await self.audit(
            who, action, outcome="refused", status=429, detail=detail,
            vehicle_id=vehicle_id, target=target, request=request,
        )  # fmt: skip
        raise ApiError(429, detail, headers={"Retry-After": str(max(1, round(wait)))})

    async def audit(
        self,
        who: Principal | None,
        action: str,
        *,
        outcome: str,
        status: int,
        detail: str | None = None,
        vehicle_id: str | None = None,
        target: str | None = None,
        request: dict[str, Any] | None = None,
        command_id: str | None = None,
    ) -> None:
        """Append to the audit log. What the client sent is stored as it can be: text
        clipped to its column, NUL characters (which PostgreSQL text cannot hold) as U+FFFD,
        non-finite numbers (which JSON cannot hold) as strings, so that a refusal of odd
        input is recorded instead of failing."""
        await self.db(
            q.add_audit,
            {
                "ts": time.time(),
                "key_id": who.key_id if who else None,
                "key_name": who.name if who else None,
                "role": who.role if who else None,
                "action": _clip(action, 64),
                "vehicle_id": _clip(vehicle_id, 64),
                "target": _clip(target, 200),
                "request": _json_safe(request) if request is not None else None,
                "outcome": outcome,
                "status_code": status,
                "detail": _clip(detail, 2000),
                "command_id": _clip(command_id, 36),
            },
        )


def _clip(text: str | None, limit: int) -> str | None:
    """`text` fit for a text column of `limit` characters (NUL replaced, the end cut)."""
    if not text:
        return text
    text = text.replace("\x00", "\ufffd")
    return text if len(text) <= limit else text[: limit - 1] + "\u2026"


def _json_safe(value: Any) -> Any:
    """`value` as JSON and PostgreSQL can store it (see Runtime.audit)."""
    if isinstance(value, float) and not math.isfinite(value):
        return repr(value)
    if isinstance(value, str):
        return value.replace("\x00", "\ufffd")
    if isinstance(value, dict):
        return {_json_safe(str(k)): _json_safe(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_json_safe(v) for v in value]
    return value


def runtime_of(request: Request) -> Runtime:
    """The running gateway."""
    rt: Runtime = request.app.state.rt
    return rt


async def get_rt(request: Request) -> Runtime:
    """The running gateway, as a dependency (a coroutine: FastAPI runs a plain function
    dependency in its thread pool, a thread hop on every request)."""
    return runtime_of(request)


_bearer = HTTPBearer(auto_error=False, description="An API key: `Authorization: Bearer eqgw_...`")


async def authenticate(rt: Runtime, token: str | None) -> Principal | None:
    """The principal of a key, or None when missing, unknown or revoked."""
    if not token:
        return None
    hit, principal = rt.keys.cached(token)
    if hit:
        return principal
    return await asyncio.to_thread(rt.keys.lookup, token)


def _action_of(request: Request) -> str:
    route = request.scope.get("route")
    path = getattr(route, "path", request.url.path)
    return f"{request.method} {path}"


def require(role: str, *, audited: bool = False) -> Callable[..., Awaitable[Principal]]:
    """A dependency admitting keys whose role includes `role` (401 without a key, 403 below)."""

    async def dependency(
        request: Request,
        creds: HTTPAuthorizationCredentials | None = Depends(_bearer),  # noqa: B008
    ) -> Principal:
        rt = runtime_of(request)
        principal = await authenticate(rt, creds.credentials if creds else None)
        if principal is None:
            if audited:
                await rt.audit(
                    None,
                    _action_of(request),
                    outcome="refused",
                    status=401,
                    detail="missing, unknown or revoked key",
                    vehicle_id=request.path_params.get("vehicle_id"),
                )
            raise ApiError(
                401,
                "a valid API key is required (Authorization: Bearer <key>)",
                headers={"WWW-Authenticate": "Bearer"},
            )
        if not principal.allows(role):
            detail = f"the {principal.role} role cannot do this; it needs {role}"
            if audited:
                await rt.audit(
                    principal,
                    _action_of(request),
                    outcome="refused",
                    status=403,
                    detail=detail,
                    vehicle_id=request.path_params.get("vehicle_id"),
                )
            raise ApiError(403, detail)
        request.state.principal = principal
        return principal

    if audited:
        _AUDITED.add(dependency)
    return dependency


# The key checks of write routes: a write refused before its endpoint runs (a body that is
# not JSON or fails validation) is audited like the endpoint's own refusals.
_AUDITED: set[Callable[..., Any]] = set()


async def audit_invalid_write(request: Request, status: int, detail: str, body: Any) -> None:
    """Audit a request to a write route refused for its body or parameters (called by the
    validation error handler; a request to any other route is not a write and is left)."""
    route = request.scope.get("route")
    dependant = getattr(route, "dependant", None)
    if dependant is None or not any(d.call in _AUDITED for d in dependant.dependencies):
        return
    rt: Runtime | None = getattr(request.app.state, "rt", None)
    if rt is None:
        return
    who: Principal | None = getattr(request.state, "principal", None)
    if who is None:  # a body that is not JSON is refused before the key check runs
        scheme, _, token = request.headers.get("authorization", "").partition(" ")
        who = await authenticate(rt, token.strip()) if scheme.lower() == "bearer" else None
    await rt.audit(
        who, _action_of(request), outcome="refused", status=status, detail=detail,
        vehicle_id=request.path_params.get("vehicle_id"),
        request=body if isinstance(body, dict) else None,
    )  # fmt: skip


viewer = require("viewer")
operator_write = require("operator", audited=True)
operator_read = require("operator")
admin_write = require("admin", audited=True)
admin_read = require("admin")
