"""Admin endpoints: API keys; and the audit log (operators and admins)."""

from __future__ import annotations

import asyncio
import time

from fastapi import APIRouter, Depends, Path, Query

from app.api.auth import Principal, create_key
from app.api.deps import Runtime, admin_read, admin_write, get_rt, operator_read
from app.api.errors import ApiError
from app.api.fleet import time_filter
from app.api.responses import JsonResponse
from app.api.schemas import MAX_ID, KeyCreate, KeyCreated, KeyOut, errors
from app.store import api_queries as q

router = APIRouter(tags=["admin"], responses=errors(401, 403))


@router.post("/keys", status_code=201, response_model=KeyCreated, responses=errors(400, 422, 429))
async def post_key(
    body: KeyCreate,
    who: Principal = Depends(admin_write),  # noqa: B008
    rt: Runtime = Depends(get_rt),  # noqa: B008
) -> JsonResponse:
    """Create a key; the key is in this response only."""
    await rt.check_write_rate(who, "key.create")
    key_id, key = await asyncio.to_thread(create_key, rt.engine, body.name, body.role)
    await rt.audit(
        who, "key.create", outcome="accepted", status=201, target=f"key {key_id}",
        request=body.model_dump(),
    )  # fmt: skip
    rows = await rt.db(q.list_keys)
    row = next(r for r in rows if r["id"] == key_id)
    return JsonResponse({**row, "key": key}, status_code=201)


@router.get("/keys", response_model=list[KeyOut])
async def get_keys(
    _who: Principal = Depends(admin_read),  # noqa: B008
    rt: Runtime = Depends(get_rt),  # noqa: B008
) -> JsonResponse:
    """Every key (without the keys themselves)."""
    return JsonResponse(await rt.db(q.list_keys))


@router.delete("/keys/{key_id}", response_model=KeyOut, responses=errors(404))
async def delete_key(
    key_id: int = Path(ge=1, le=MAX_ID),
    who: Principal = Depends(admin_write),  # noqa: B008
    rt: Runtime = Depends(get_rt),  # noqa: B008
) -> JsonResponse:
    """Revoke a key at once."""
    done = await rt.db(q.revoke_key, key_id, time.time())
    rt.keys.forget()
    if not done:
        await rt.audit(who, "key.revoke", outcome="refused", status=404, target=f"key {key_id}")
        raise ApiError(404, f"no active key {key_id}", "unknown_key")
    await rt.audit(who, "key.revoke", outcome="accepted", status=200, target=f"key {key_id}")
    rows = await rt.db(q.list_keys)
    return JsonResponse(next(r for r in rows if r["id"] == key_id))


@router.get("/audit", responses=errors(422), summary="Who did what, when, with which key")
async def get_audit(
    from_: str | None = Query(default=None, alias="from", description="Epoch s or ISO 8601"),
    to: str | None = Query(default=None, description="Epoch s or ISO 8601"),
    vehicle: str | None = Query(default=None, max_length=64),
    key_id: int | None = Query(default=None, ge=1, le=MAX_ID),
    limit: int = Query(default=100, ge=1, le=10000),
    _who: Principal = Depends(operator_read),  # noqa: B008
    rt: Runtime = Depends(get_rt),  # noqa: B008
) -> JsonResponse:
    start, end = time_filter(from_, to)
    rows = await rt.db(
        q.list_audit,
        start=start,
        end=end,
        vehicle_id=vehicle,
        key_id=key_id,
        limit=limit,
    )
    return JsonResponse({"entries": rows})
