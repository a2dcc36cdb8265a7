"""Who may call a route, declared by one parameter's type (`who: OperatorWrite`), and the
vehicle a route acts on, resolved within the caller's scope (`vehicle_id: VehicleId`): keys
and session cookies resolved once per request, refusals audited (polar's `auth.py`)."""

from __future__ import annotations

import asyncio
import hmac
from collections.abc import Awaitable, Callable, Mapping, MutableMapping
from typing import Annotated, Any, TypeVar

from fastapi import Depends, Request
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer
from sqlalchemy.exc import InterfaceError, OperationalError
from sqlalchemy.exc import TimeoutError as PoolTimeout

from eqgw.security.keys import Principal, SessionAuth
from eqgw.store.engine import health_of, unavailable_error
from eqgw.web.errors import ApiError
from eqgw.web.runtime import Runtime, runtime_of

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
                    principal,
                    _action_of(request),
                    outcome="refused",
                    status=403,
                    detail=detail,
                    vehicle_id=request.path_params.get("vehicle_id"),
                )
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
        who,
        _action_of(request),
        outcome="refused",
        status=status,
        detail=detail,
        vehicle_id=request.path_params.get("vehicle_id"),
        request=body if isinstance(body, dict) else None,
    )


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
                who,
                audit_action,
                outcome="refused",
                status=404,
                detail=f"{vehicle_id} is outside the key's scope",
                vehicle_id=vehicle_id,
                request=body if isinstance(body, dict) else None,
            )
        raise refusal

    VEHICLE_SCOPE_DEPENDENCIES.add(vehicle_in_scope)
    return vehicle_in_scope


# A route's vehicle, resolved within the caller's scope (`vehicle_id: VehicleId`).
VehicleId = Annotated[str, Depends(in_scope())]


def scope_filter(who: Principal) -> list[str] | None:
    """The vehicle ids a store query is limited to for this key (None: the whole fleet)."""
    ids = who.scope.vehicle_ids()
    return None if ids is None else sorted(ids)


def vehicles_of(rt: Runtime, who: Principal, depot: str | None) -> list[str] | None:
    """The vehicle ids a query is limited to: the key's scope, and with `depot` the vehicles
    the fleet file puts in that depot (as a key's depot scope resolves them); None for all."""
    ids = scope_filter(who)
    if depot is None:
        return ids
    of_depot = {v.id for v in rt.settings.vehicles if v.depot == depot}
    if ids is not None:
        of_depot &= set(ids)
    return sorted(of_depot)


viewer = require("viewer")
operator_write = require("operator", audited=True)
operator_read = require("operator")
admin_write = require("admin", audited=True)
admin_read = require("admin")
fleet_admin_write = require("admin", audited=True, fleet_wide=True)
fleet_admin_read = require("admin", fleet_wide=True)

# A route declares who may call it by the type of one parameter (`who: OperatorWrite`); the
# `*Write` ones also audit the request, refused or not.
Viewer = Annotated[Principal, Depends(viewer)]
OperatorRead = Annotated[Principal, Depends(operator_read)]
OperatorWrite = Annotated[Principal, Depends(operator_write)]
AdminRead = Annotated[Principal, Depends(admin_read)]
AdminWrite = Annotated[Principal, Depends(admin_write)]
FleetAdminRead = Annotated[Principal, Depends(fleet_admin_read)]
FleetAdminWrite = Annotated[Principal, Depends(fleet_admin_write)]
