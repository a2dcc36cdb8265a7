"""Liveness, readiness (database and buses; alerting reported) and Prometheus metrics."""

from __future__ import annotations

import asyncio
from typing import Any

from fastapi import APIRouter, Depends, Request
from fastapi.responses import Response
from prometheus_client import CONTENT_TYPE_LATEST
from sqlalchemy import text

from app.api.deps import Runtime, get_rt
from app.api.responses import JsonResponse
from app.describe import describe

router = APIRouter(tags=["health"])
_ENGINE = ("running", "last_error", "last_error_at", "backlog", "open", "rules", "resyncs")


@router.get("/healthz", summary="The process is up")
async def healthz() -> JsonResponse:
    return JsonResponse({"status": "ok"})


@router.get(
    "/readyz",
    summary="Database reachable and buses open (503 otherwise); alerting's state reported",
    responses={503: {"description": "not ready"}},
)
async def readyz(request: Request, rt: Runtime = Depends(get_rt)) -> JsonResponse:  # noqa: B008
    def ping(conn: Any) -> None:
        conn.execute(text("SELECT 1"))

    db: dict[str, Any] = {"ok": True}
    try:
        await asyncio.wait_for(rt.db(ping), timeout=5.0)
    except Exception as exc:
        db = {"ok": False, "error": describe(exc)}
    status = rt.ingest.status()
    w = status["writer"]
    # A database that answers a read but refuses the writer (a SQLite file another process
    # holds the write lock of, a full disk, a read-only replica) is not ready either.
    db["writer"] = {k: w[k] for k in ("state", "pending_rows", "lag_s", "consecutive_failures")}
    if db["ok"] and w["consecutive_failures"]:
        db["ok"] = False
        db["error"] = f"writes failing ({w['consecutive_failures']} in a row): {w['last_error']}"
    buses = [
        {"name": b["name"], "state": b["state"], "last_error": b["last_error"]}
        for b in status["buses"]
    ]
    # Ready when the database answers and some bus is open; a dead bus on one vehicle must
    # not take the whole gateway out of a load balancer.
    buses_ok = not buses or any(b["state"] == "open" for b in buses)
    ready = db["ok"] and buses_ok
    body: dict[str, Any] = {"ready": ready, "database": db, "buses": buses}
    cluster = getattr(request.app.state, "cluster", None)
    if cluster is not None:  # one gateway of several on one PostgreSQL: who reads which bus
        body["cluster"] = cluster.status()
    # Alerting is reported, not part of readiness: a stopped engine or a webhook receiver that
    # is down does not stop this gateway serving the API and ingesting (events wait in the
    # outbox); `eqgw_alert_engine_running` and `eqgw_webhook_pending` are what to page on.
    engine = getattr(request.app.state, "alerts", None)
    body["alerts"] = (
        {"enabled": False}
        if engine is None
        else {"enabled": True, **{k: v for k, v in engine.status().items() if k in _ENGINE}}
    )
    delivery = getattr(request.app.state, "delivery", None)
    if delivery is not None:
        body["delivery"] = delivery.status()
    return JsonResponse(body, status_code=200 if ready else 503)


@router.get("/metrics", summary="Prometheus metrics", response_class=Response)
async def metrics(request: Request) -> Response:
    body = request.app.state.metrics.exposition(getattr(request.app.state, "alerts", None))
    return Response(body, media_type=CONTENT_TYPE_LATEST)
