"""What routers share: the running gateway (`Runtime`), key checks by role, audit, rate limits."""

from __future__ import annotations

import asyncio
import hmac
import math
import time
from collections.abc import Awaitable, Callable, Mapping, MutableMapping
from dataclasses import dataclass, field
from typing import Annotated, Any, Concatenate, TypeVar

from fastapi import Depends, Request
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer
from sqlalchemy import Connection, Engine
from sqlalchemy.exc import InterfaceError, OperationalError
from sqlalchemy.exc import TimeoutError as PoolTimeout

from eqgw.commands.service import CommandService
from eqgw.config import Settings
from eqgw.ingest.service import IngestService
from eqgw.security import limit_repository as limit_queries
from eqgw.security import repository as q
from eqgw.security.audit import AnonymousRefusals
from eqgw.security.keys import KeyAuthenticator, Person, Principal, SessionAuth
from eqgw.store.engine import health_of, unavailable_error
from eqgw.store.history_cache import HistoryCache
from eqgw.store.transaction import P, R, run_in_transaction
from eqgw.web.errors import ApiError
from eqgw.web.settings import ApiSettings


class RateLimiter:
    """Sliding-window limit of writes per key, kept in the database (app/store/limit_queries):
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
    # Follows the fleet in the database (eqgw.fleet.sync.FleetSync); set by the lifespan.
    fleet_sync: Any = None
    refusals: AnonymousRefusals = field(default_factory=AnonymousRefusals)
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
        person: Person | None = None,
    ) -> None:
        """Append to the audit log. What the client sent is stored as it can be: text
        clipped to its column, NUL characters (which PostgreSQL text cannot hold) as U+FFFD,
        non-finite numbers (which JSON cannot hold) as strings, so that a refusal of odd
        input is recorded instead of failing. A refusal without a valid key is counted and
        written with the others of its action at the next flush (eqgw.security.audit), unless
        it names a `person` (one the OpenID provider vouched for, refused a session). The
        person of a single sign-on session is named (subject, email) with its key."""
        if who is None and outcome == "refused" and person is None:
            self.refusals.add(_clip(action, 64) or "", status, detail, vehicle_id)
            return
        if person is None and who is not None:
            person = who.person
        await self.db(
            q.add_audit,
            audit_entry(
                who,
                action,
                outcome=outcome,
                status=status,
                detail=detail,
                vehicle_id=vehicle_id,
                target=target,
                request=request,
                command_id=command_id,
                person=person,
            ),
        )


def audit_entry(
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
    key_name: str | None = None,
    person: Person | None = None,
) -> dict[str, Any]:
    """An audit log row as `Runtime.audit` writes it, for an entry written in the same
    transaction as the change it records (`key_name`: who, without a key: a command line;
    the person of a single sign-on session is the key's own unless given)."""
    if person is None and who is not None:
        person = who.person
    return {
        "ts": time.time(),
        "key_id": who.key_id if who else None,
        "key_name": _clip(who.name if who else key_name, 200),
        "role": who.role if who else None,
        "action": _clip(action, 64),
        "vehicle_id": _clip(vehicle_id, 64),
        "target": _clip(target, 200),
        "request": _json_safe(request) if request is not None else None,
        "outcome": outcome,
        "status_code": status,
        "detail": _clip(detail, 2000),
        "command_id": _clip(command_id, 36),
        "subject": _clip(person.subject, 255) if person else None,
        "email": _clip(person.email, 320) if person else None,
    }


def _clip(text: str | None, limit: int) -> str | None:
    """`text` fit for a text column of `limit` characters (NUL replaced, the end cut)."""
    if not text:
        return text
    text = _storable(text)
    return text if len(text) <= limit else text[: limit - 1] + "\u2026"


def _storable(text: str) -> str:
    """`text` with NUL characters and lone surrogates replaced by U+FFFD."""
    text = text.replace("\x00", "\ufffd")
    try:
        text.encode("utf-8")
    except UnicodeEncodeError:
        text = text.encode("utf-8", "surrogatepass").decode("utf-8", "replace")
    return text


def _json_safe(value: Any) -> Any:
    """`value` as JSON and PostgreSQL can store it (see Runtime.audit)."""
    if isinstance(value, float) and not math.isfinite(value):
        return repr(value)
    if isinstance(value, str):
        return _storable(value)
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


_Found = TypeVar("_Found")

_bearer = HTTPBearer(auto_error=False, description="An API key: `Authorization: Bearer eqgw_...`")
_BearerCreds = Annotated[HTTPAuthorizationCredentials | None, Depends(_bearer)]


async def authenticate(rt: Runtime, token: str | None) -> Principal | None:
    """The principal of a key, or None when missing, unknown or revoked."""
    return await _resolve(rt, token, rt.keys.cached, rt.keys.lookup, rt.keys.last_known)


async def _resolve(
    rt: Runtime,
    token: str | None,
    cached: Callable[[str], tuple[bool, _Found | None]],
    lookup: Callable[[str], _Found | None],
    last_known: Callable[[str], tuple[bool, _Found | None]],
) -> _Found | None:
    """What a token stands for: from the cache when it answers, else looked up in a thread.
    The database away (failing now, or moments ago), the last answer it gave for the token
    stands: reading the live view needs no database."""
    if not token:
        return None
    hit, found = cached(token)
    if hit:
        return found
    health = health_of(rt.engine)
    error: Exception = unavailable_error()
    if not health.down():
        try:
            return await asyncio.to_thread(lookup, token)
        except (OperationalError, InterfaceError, PoolTimeout) as exc:
            health.failed()
            error = exc
    known, found = last_known(token)
    if known:
        return found
    raise error


SESSION_COOKIE = "eqgw_session"
CSRF_HEADER = "X-CSRF-Token"
SAFE_METHODS = frozenset({"GET", "HEAD", "OPTIONS"})


async def authenticate_session(rt: Runtime, token: str | None) -> SessionAuth | None:
    """The browser session of a cookie (its key resolved as a key is), or None."""
    keys = rt.keys
    return await _resolve(
        rt, token, keys.cached_session, keys.lookup_session, keys.last_known_session
    )


def session_cookie(headers: Mapping[str, str]) -> str | None:
    """The session cookie's value among a request's headers (lower-case names), if any."""
    for part in headers.get("cookie", "").split(";"):
        name, _, value = part.strip().partition("=")
        if name == SESSION_COOKIE and value:
            return value
    return None


Auth = tuple[Principal, SessionAuth | None]
_RESOLVED = "eqgw_auth"  # a request's resolved credentials, in its ASGI scope's state


def remember_auth(scope: MutableMapping[str, Any], auth: Auth | None) -> None:
    """Keep what a request's credentials resolved to for the rest of the request."""
    scope.setdefault("state", {})[_RESOLVED] = (auth,)


async def request_auth(rt: Runtime, request: Request) -> Auth | None:
    """Who a request is from: resolved once per request (the request guard may have)."""
    kept = request.scope.get("state", {}).get(_RESOLVED)
    if kept is not None:
        auth: Auth | None = kept[0]
        return auth
    auth = await resolve_headers(rt, request.headers)
    remember_auth(request.scope, auth)
    return auth


async def resolve_headers(rt: Runtime, headers: Mapping[str, str]) -> Auth | None:
    """Who a request is from its headers: a Bearer key, else a session cookie; None if
    neither is valid. A Bearer header present decides alone (no fallback to the cookie)."""
    scheme, _, token = headers.get("authorization", "").partition(" ")
    if scheme.lower() == "bearer":
        principal = await authenticate(rt, token.strip())
        return (principal, None) if principal is not None else None
    session = await authenticate_session(rt, session_cookie(headers))
    return (session.principal, session) if session is not None else None


def _action_of(request: Request) -> str:
    route = request.scope.get("route")
    path = getattr(route, "path", request.url.path)
    return f"{request.method} {path}"


def require(
    role: str, *, audited: bool = False, fleet_wide: bool = False
) -> Callable[..., Awaitable[Principal]]:
    """A dependency admitting keys whose role includes `role` (401 without a key, 403 below);
    with `fleet_wide`, only keys whose scope is the whole fleet (403 for a scoped key: the
    route acts on every vehicle, as webhooks do)."""

    async def dependency(
        request: Request,
        # Read from the headers below (a key, else the session cookie); here for the docs.
        _creds: _BearerCreds,
    ) -> Principal:
        rt = runtime_of(request)
        resolved = await request_auth(rt, request)
        principal, session = resolved if resolved is not None else (None, None)
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
        detail = None
        if (
            session is not None
            and request.method not in SAFE_METHODS
            and not hmac.compare_digest(
                request.headers.get(CSRF_HEADER, "").encode(), session.csrf_token.encode()
            )
        ):
            # A write by cookie must prove it comes from the dashboard's own page.
            detail = f"a write with a session cookie needs the session's {CSRF_HEADER} header"
            if audited:
                await rt.audit(
                    principal, _action_of(request), outcome="refused", status=403,
                    detail=detail, vehicle_id=request.path_params.get("vehicle_id"),
                )  # fmt: skip
            raise ApiError(403, detail, "csrf")
        # A person's grants: the vehicles where they hold `role` (keys: their scope).
        acting = principal.acting_as(role)
        vehicle_id = request.path_params.get("vehicle_id")
        if not principal.allows(role):
            detail = f"the {principal.role} role cannot do this; it needs {role}"
        elif fleet_wide and not acting.scope.everything:
            detail = "this acts on the whole fleet: a key scoped to depots or vehicles cannot"
        elif vehicle_id is not None and principal.sees(vehicle_id) and not acting.sees(vehicle_id):
            there = principal.role_for(vehicle_id)
            detail = f"you are {there} of vehicle {vehicle_id}; this needs {role}"
        if detail is not None:
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
        return acting

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
    # Resolved already by the key check or the request guard, else (a body that is not JSON
    # is refused before the key check runs) now.
    resolved = await request_auth(rt, request)
    who = resolved[0] if resolved is not None else None
    await rt.audit(
        who, _action_of(request), outcome="refused", status=status, detail=detail,
        vehicle_id=request.path_params.get("vehicle_id"),
        request=body if isinstance(body, dict) else None,
    )  # fmt: skip


def unknown_vehicle(vehicle_id: str) -> ApiError:
    """The 404 of a vehicle that does not exist, or is outside the caller's scope: the same
    answer for both, so a scoped key cannot tell another depot's vehicles exist."""
    return ApiError(404, f"no vehicle {vehicle_id!r}", "unknown_vehicle")


# Every dependency `in_scope` made: a route with `{vehicle_id}` in its path must have one
# (tests/test_scope_walk.py walks the OpenAPI document's routes and checks).
VEHICLE_SCOPE_DEPENDENCIES: set[Callable[..., Awaitable[str]]] = set()


def in_scope(audit_action: str | None = None) -> Callable[..., Awaitable[str]]:
    """The dependency that resolves the path's `vehicle_id` within the caller's scope: the id,
    or the 404 an unknown vehicle gets (`unknown_vehicle`). Declared after the role
    dependency, so a request without a key is a 401 first. With `audit_action`, a refusal is
    audited under that action (the write routes)."""

    async def vehicle_in_scope(request: Request, vehicle_id: str) -> str:
        rt = runtime_of(request)
        resolved = await request_auth(rt, request)
        who = resolved[0] if resolved is not None else None
        if who is not None and who.sees(vehicle_id):
            return vehicle_id
        refusal = unknown_vehicle(vehicle_id)
        if audit_action is not None:
            try:
                body = await request.json()
            except ValueError:
                body = None
            await rt.audit(
                who, audit_action, outcome="refused", status=404,
                detail=f"{vehicle_id} is outside the key's scope", vehicle_id=vehicle_id,
                request=body if isinstance(body, dict) else None,
            )  # fmt: skip
        raise refusal

    VEHICLE_SCOPE_DEPENDENCIES.add(vehicle_in_scope)
    return vehicle_in_scope


# A route's vehicle, resolved within the caller's scope (`vehicle_id: VehicleId`).
VehicleId = Annotated[str, Depends(in_scope())]


def scope_filter(who: Principal) -> list[str] | None:
    """The vehicle ids a store query is limited to for this key (None: the whole fleet)."""
    ids = who.scope.vehicle_ids()
    return None if ids is None else sorted(ids)


viewer = require("viewer")
operator_write = require("operator", audited=True)
operator_read = require("operator")
admin_write = require("admin", audited=True)
admin_read = require("admin")
fleet_admin_write = require("admin", audited=True, fleet_wide=True)
fleet_admin_read = require("admin", fleet_wide=True)

# A route declares who may call it by the type of one parameter (`who: OperatorWrite`); the
# `*Write` ones also audit the request, refused or not.
Rt = Annotated[Runtime, Depends(get_rt)]
Viewer = Annotated[Principal, Depends(viewer)]
OperatorRead = Annotated[Principal, Depends(operator_read)]
OperatorWrite = Annotated[Principal, Depends(operator_write)]
AdminRead = Annotated[Principal, Depends(admin_read)]
AdminWrite = Annotated[Principal, Depends(admin_write)]
FleetAdminRead = Annotated[Principal, Depends(fleet_admin_read)]
FleetAdminWrite = Annotated[Principal, Depends(fleet_admin_write)]
