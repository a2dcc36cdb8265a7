"""Admin endpoints: API keys; and the audit log (operators and admins)."""

from __future__ import annotations

import asyncio
import time
from typing import Any

from fastapi import APIRouter, Path, Query, Request
from fastapi.responses import Response, StreamingResponse
from sqlalchemy import Connection

from eqgw.security import repository as q
from eqgw.security.auth import AdminRead, AdminWrite, OperatorRead, vehicles_of
from eqgw.security.keys import (
    EVERYTHING,
    INGEST,
    KeyNotFound,
    Principal,
    Scope,
    create_key,
    key_summary,
    rotate_key,
    scope_of,
)
from eqgw.security.schemas import (
    AuditList,
    KeyCreate,
    KeyCreated,
    KeyOut,
    KeyRotate,
    KeyRotated,
    KeyScope,
)
from eqgw.web import csv_export
from eqgw.web.errors import ApiError
from eqgw.web.responses import JsonResponse
from eqgw.web.runtime import Rt, Runtime
from eqgw.web.schemas import MAX_ID, errors
from eqgw.web.times import time_filter

router = APIRouter(tags=["admin"], responses=errors(401, 403))


def _scope(given: KeyScope | str | None, who: Principal) -> Scope:
    if given is None:
        return who.scope  # a scoped admin's keys are scoped like it unless told narrower
    if given == "all":
        return EVERYTHING
    assert isinstance(given, KeyScope)
    if given.all:
        return EVERYTHING
    return Scope.of(given.groups, given.vehicles)


# An ingest key of the whole fleet uploads for every vehicle: made only when asked for.
INGEST_NEEDS_SCOPE = (
    'an ingest key needs a scope: {"vehicles": [...]} or {"groups": [...]} (the vehicles its '
    'forwarder uploads for), or {"all": true} for a relay that uploads for every vehicle'
)


async def _summary(rt: Runtime, key_id: int) -> dict[str, Any]:
    """The key's summary as stored now; a key gone in between (deleted by another request or
    gateway) is a 404, not a 500."""
    row = await rt.db(q.get_key, key_id)
    if row is None:
        raise ApiError(404, f"no key {key_id}", "unknown_key")
    return key_summary(row)


@router.post(
    "/keys", status_code=201, response_model=KeyCreated, responses=errors(400, 403, 422, 429)
)
async def post_key(
    body: KeyCreate,
    who: AdminWrite,
    rt: Rt,
) -> JsonResponse:
    """Create a key; the key is in this response only. A scoped admin creates keys within
    its own scope only (403 for a wider one); a key without `scope` gets the creator's."""
    req = body.model_dump()
    await rt.check_write_rate(who, "key.create", request=req)
    scope = _scope(body.scope, who)
    if body.role == INGEST and body.scope is None and scope.everything:
        await rt.audit(
            who, "key.create", outcome="refused", status=422, detail=INGEST_NEEDS_SCOPE, request=req
        )
        raise ApiError(422, INGEST_NEEDS_SCOPE, "scope_required")
    if not scope.within(who.scope):
        detail = "a key's scope must lie within the scope of the key creating it"
        await rt.audit(who, "key.create", outcome="refused", status=403, detail=detail, request=req)
        raise ApiError(403, detail, "out_of_scope")
    try:
        expires_at = body.expiry(time.time())
    except ValueError as exc:
        await rt.audit(
            who, "key.create", outcome="refused", status=422, detail=str(exc), request=req
        )
        raise ApiError(422, str(exc)) from exc
    key_id, key = await asyncio.to_thread(
        create_key, rt.engine, body.name, body.role, scope=scope, expires_at=expires_at
    )
    await rt.audit(
        who,
        "key.create",
        outcome="accepted",
        status=201,
        target=f"key {key_id}",
        request=req,
    )
    return JsonResponse({**await _summary(rt, key_id), "key": key}, status_code=201)


@router.get("/keys", response_model=list[KeyOut])
async def get_keys(
    who: AdminRead,
    rt: Rt,
) -> JsonResponse:
    """Every key (without the keys themselves); a scoped admin sees the keys within its
    scope only."""
    rows = await rt.db(q.list_keys)
    now = time.time()
    return JsonResponse([key_summary(r, now) for r in rows if scope_of(r).within(who.scope)])


async def _managed_key(rt: Runtime, who: Principal, key_id: int) -> dict[str, Any] | None:
    """The key `key_id` if the caller may manage it (its scope within the caller's)."""
    row: dict[str, Any] | None = await rt.db(q.get_key, key_id)
    if row is None or not scope_of(row).within(who.scope):
        return None
    return row


@router.delete("/keys/{key_id}", response_model=KeyOut, responses=errors(404))
async def delete_key(
    *,
    key_id: int = Path(ge=1, le=MAX_ID),
    who: AdminWrite,
    rt: Rt,
) -> JsonResponse:
    """Revoke a key at once (one in a rotation's overlap too)."""
    done = False
    if await _managed_key(rt, who, key_id) is not None:
        done = await rt.db(q.revoke_key, key_id, time.time())
    rt.keys.forget()
    if not done:
        await rt.audit(who, "key.revoke", outcome="refused", status=404, target=f"key {key_id}")
        raise ApiError(404, f"no active key {key_id}", "unknown_key")
    await rt.audit(who, "key.revoke", outcome="accepted", status=200, target=f"key {key_id}")
    return JsonResponse(await _summary(rt, key_id))


@router.post(
    "/keys/{key_id}/rotate",
    status_code=201,
    response_model=KeyRotated,
    responses=errors(400, 404, 422, 429),
)
async def post_rotate(
    *,
    body: KeyRotate,
    key_id: int = Path(ge=1, le=MAX_ID),
    who: AdminWrite,
    rt: Rt,
) -> JsonResponse:
    """Rotate a key: a new key with its name, role and scope (or a narrower `scope`), shown
    in this response only; the old key keeps working for `overlap_s` seconds (default a day),
    then is revoked."""
    req = body.model_dump()
    target = f"key {key_id}"
    await rt.check_write_rate(who, "key.rotate", target=target, request=req)
    try:
        expires_at = body.expiry(time.time())
        new_id, key, ends = await asyncio.to_thread(
            rotate_key,
            rt.engine,
            key_id,
            overlap_s=body.overlap_s,
            expires_at=expires_at,
            within=who.scope,
            scope=None if body.scope is None else _scope(body.scope, who),
        )
    except ValueError as exc:
        await rt.audit(
            who,
            "key.rotate",
            outcome="refused",
            status=422,
            detail=str(exc),
            target=target,
            request=req,
        )
        raise ApiError(422, str(exc)) from exc
    except KeyNotFound as exc:
        await rt.audit(who, "key.rotate", outcome="refused", status=404, target=target, request=req)
        raise ApiError(404, f"no active key {key_id}", "unknown_key") from exc
    rt.keys.forget()
    await rt.audit(
        who,
        "key.rotate",
        outcome="accepted",
        status=201,
        target=target,
        detail=f"replaced by key {new_id}",
        request=req,
    )
    return JsonResponse(
        {**await _summary(rt, new_id), "key": key, "replaces": key_id, "old_key_ends_at": ends},
        status_code=201,
    )


@router.get(
    "/audit",
    responses={**errors(422), 200: {"content": csv_export.CSV_CONTENT}},
    summary="Who did what, when, with which key: JSON, or CSV",
    response_model=AuditList,
)
async def get_audit(
    *,
    request: Request,
    from_: str | None = Query(default=None, alias="from", description="Epoch s or ISO 8601"),
    to: str | None = Query(default=None, description="Epoch s or ISO 8601"),
    vehicle: str | None = Query(default=None, max_length=64),
    depot: str | None = Query(default=None, max_length=200, description="the fleet file's depot"),
    key_id: int | None = Query(default=None, ge=1, le=MAX_ID),
    limit: int = Query(default=100, ge=1, le=10000),
    format: str | None = Query(
        default=None,
        pattern="^(json|csv)$",
        description="json (default), or csv: every entry that matches, oldest first, streamed "
        "(`limit` does not apply), as `Accept: text/csv` asks",
    ),
    who: OperatorRead,
    rt: Rt,
) -> Response:
    """Audit entries, newest first; a scoped key sees those of its vehicles only. With a
    depot, the entries of its vehicles only (an entry of no vehicle is of no depot)."""
    start, end = time_filter(from_, to)
    filters = {"start": start, "end": end, "vehicle_id": vehicle, "key_id": key_id}
    vehicle_ids = vehicles_of(rt, who, depot)
    if csv_export.wants_csv(request, format):
        return audit_csv(rt, vehicle_ids, **filters)
    rows = await rt.db(
        q.list_audit,
        start=start,
        end=end,
        vehicle_id=vehicle,
        key_id=key_id,
        vehicle_ids=vehicle_ids,
        limit=limit,
    )
    return JsonResponse({"entries": rows})


AUDIT_COLUMNS = (
    "id",
    "ts",
    "key_id",
    "key_name",
    "subject",
    "email",
    "role",
    "action",
    "vehicle_id",
    "target",
    "outcome",
    "status_code",
    "detail",
    "command_id",
    "request",
)


def audit_csv(rt: Runtime, vehicle_ids: list[str] | None, **filters: Any) -> StreamingResponse:
    """Audit entries (`list_audit` filters), oldest first."""

    def page(conn: Connection, after: int, limit: int) -> list[dict[str, Any]]:
        return q.list_audit(conn, vehicle_ids=vehicle_ids, after_id=after, limit=limit, **filters)

    return csv_export.stream(rt, "audit", AUDIT_COLUMNS, page)
