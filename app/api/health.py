"""Liveness, readiness (database and buses) and Prometheus metrics."""

from __future__ import annotations

import asyncio
from typing import Any

from fastapi import APIRouter, Depends, Request
from fastapi.responses import Response
from prometheus_client import CONTENT_TYPE_LATEST, generate_latest
from sqlalchemy import text

from app.api.deps import Runtime, get_rt
from app.api.responses import JsonResponse

router = APIRouter(tags=["health"])


@router.get("/healthz", summary="The process is up")
async def healthz() -> JsonResponse:
    return JsonResponse({"status": "ok"})


@router.get(
    "/readyz",
    summary="Database reachable and buses open (503 otherwise)",
    responses={503: {"description": "not ready"}},
)
async def readyz(request: Request, rt: Runtime = Depends(get_rt)) -> JsonResponse:  # noqa: B008
    def ping(conn: Any) -> None:
        conn.execute(text("SELECT 1"))

    db: dict[str, Any] = {"ok": True}
    try:
        await asyncio.wait_for(rt.db(ping), timeout=5.0)
    except Exception as exc:
        db = {"ok": False, "error": f"{type(exc).__name__}: {str(exc).splitlines()[0][:200]}"}
    buses = [
        {"name": b["name"], "state": b["state"], "last_error": b["last_error"]}
        for b in rt.ingest.status()["buses"]
    ]
    # Ready when the database answers and some bus is open; a dead bus on one vehicle must
    # not take the whole gateway out of a load balancer.
    buses_ok = not buses or any(b["state"] == "open" for b in buses)
    ready = db["ok"] and buses_ok
    body: dict[str, Any] = {"ready": ready, "database": db, "buses": buses}
    cluster = getattr(request.app.state, "cluster", None)
    if cluster is not None:  # one gateway of several on one PostgreSQL: who reads which bus
        body["cluster"] = cluster.status()
    return JsonResponse(body, status_code=200 if ready else 503)


@router.get("/metrics", summary="Prometheus metrics", response_class=Response)
async def metrics(request: Request) -> Response:
    registry = request.app.state.metrics.registry
    return Response(generate_latest(registry), media_type=CONTENT_TYPE_LATEST)
