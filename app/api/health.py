"""Liveness, readiness (database and buses; alerting reported) and Prometheus metrics."""

from __future__ import annotations

import asyncio
import hmac
import re
from typing import Any

from fastapi import APIRouter, Request
from fastapi.responses import Response
from prometheus_client import CONTENT_TYPE_LATEST
from pydantic import BaseModel, Field
from sqlalchemy import text

from eqgw.describe import describe
from eqgw.security.auth import resolve_headers
from eqgw.web.responses import JsonResponse
from eqgw.web.runtime import Rt, Runtime


class Health(BaseModel):
    """The process answers."""

    status: str


class WriterState(BaseModel):
    """The batched writer."""

    state: str
    pending_rows: int
    lag_s: float | None
    consecutive_failures: int


class DatabaseState(BaseModel):
    """Whether the database answers and takes writes."""

    ok: bool
    error: str | None = None
    writer: WriterState


class BusState(BaseModel):
    """One configured bus."""

    name: str
    state: str
    last_error: str | None


class Readiness(BaseModel):
    """Ready when the database answers and takes writes and some bus is open."""

    ready: bool
    # The details below only with a whole-fleet admin key or the metrics token (a load
    # balancer, and any key scoped to depots or vehicles, sees `ready` alone).
    database: DatabaseState | None = None
    buses: list[BusState] | None = None
    alerts: dict[str, Any] | None = Field(
        default=None, description="the alert engine's state (reported only)"
    )
    delivery: dict[str, Any] | None = Field(
        default=None, description="webhook and MQTT delivery (reported only)"
    )
    telemetry: dict[str, Any] | None = Field(
        default=None, description="MQTT telemetry, when enabled (reported only)"
    )
    cluster: dict[str, Any] | None = Field(
        default=None, description="several gateways on one PostgreSQL: who reads which bus"
    )
    fleet: dict[str, Any] | None = Field(
        default=None,
        description="the fleet's version this gateway runs (vehicles, buses, when applied)",
    )
    warm_up: dict[str, Any] | None = Field(
        default=None,
        description="the API's route tables built before ready: done, seconds",
    )


router = APIRouter(tags=["health"])
_ENGINE = ("running", "last_error", "last_error_at", "backlog", "open", "rules", "resyncs")


@router.get("/healthz", summary="The process is up", response_model=Health)
async def healthz() -> JsonResponse:
    return JsonResponse({"status": "ok"})


@router.get(
    "/readyz",
    summary="Database reachable and buses open (503 otherwise); alerting's state reported",
    responses={503: {"description": "not ready", "model": Readiness}},
    response_model=Readiness,
)
async def readyz(request: Request, rt: Rt) -> JsonResponse:
    """Without credentials only `ready` (what a load balancer needs); the details (buses,
    cluster, alerting, delivery errors) with a whole-fleet admin key or the metrics token."""

    def ping(conn: Any) -> None:
        conn.execute(text("SELECT 1"))

    db: dict[str, Any] = {"ok": True}
    try:
        async with asyncio.timeout(5.0):
            await rt.db(ping)
    except Exception as exc:
        db = {"ok": False, "error": describe(exc)}
    status = rt.ingest.status()
    w = status["writer"]
    # A database that answers a read but refuses the writer (a SQLite file another process
    # holds the write lock of, a full disk, a read-only replica) is not ready either.
    db["writer"] = {
        k: w[k] for k in ("state", "pending_rows", "journal_rows", "lag_s", "consecutive_failures")
    }
    if db["ok"] and w["consecutive_failures"]:
        db["ok"] = False
        db["error"] = f"writes failing ({w['consecutive_failures']} in a row): {w['last_error']}"
    elif db["ok"] and w["state"] == "dead":  # the writer thread is gone: nothing is written
        db["ok"] = False
        db["error"] = "the database writer is not running"
    buses = [
        {
            "name": b["name"],
            "state": b["state"],
            "stalled": b.get("stalled", False),
            "last_error": b["last_error"],
        }
        for b in status["buses"]
    ]
    # Ready when the database answers and some bus is open and draining (a stalled socketcand
    # link takes no frames); a dead bus on one vehicle must not take the whole gateway out of
    # a load balancer.
    buses_ok = not buses or any(b["state"] == "open" and not b["stalled"] for b in buses)
    # Background tasks: one backing off is reported; one failed for good is not ready (a fatal
    # fault: the process is ending with it; a bug: it stays failed until a restart), unless it
    # only reports (`critical` false: alert delivery, telemetry).
    tasks = [t for t in status.get("tasks", []) if t["state"] in ("backoff", "failed")]
    failed = any(t["state"] == "failed" and t.get("critical", True) for t in tasks)
    # The API's lazily built parts built (app/api/warmup.py): the first requests are not slow.
    warm_up_s = getattr(request.app.state, "warm_up_s", None)
    warm = warm_up_s is not None
    ready = warm and db["ok"] and buses_ok and not failed
    body: dict[str, Any] = {
        "ready": ready,
        "database": db,
        "buses": buses,
        "tasks": tasks,
        "warm_up": {"done": warm, "seconds": warm_up_s},
    }
    cluster = getattr(request.app.state, "cluster", None)
    if cluster is not None:  # one gateway of several on one PostgreSQL: who reads which bus
        body["cluster"] = cluster.status()
    if rt.fleet_sync is not None:  # the fleet's version this gateway runs
        body["fleet"] = rt.fleet_sync.status()
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
    # MQTT telemetry is reported likewise: a broker that is away stops no ingest.
    telemetry = getattr(request.app.state, "telemetry", None)
    if telemetry is not None:
        body["telemetry"] = telemetry.status()
    code = 200 if ready else 503
    if not await may_see_details(request, rt):
        return JsonResponse({"ready": ready}, status_code=code)
    return JsonResponse(body, status_code=code)


# Labels that name this fleet's buses, vehicles, gateways or receivers: left out of /metrics
# without credentials, with the series that carry them.
_NAMING_LABELS = re.compile(rb'[{,](?:bus|vehicle|vehicle_id|instance|webhook|channel|task)="')


async def may_see_details(request: Request, rt: Runtime) -> bool:
    """Whether the request carries the metrics token or a whole-fleet admin key (or such an
    admin's session). The details name every bus, vehicle, gateway and webhook of the
    fleet, so a key scoped to depots or vehicles, an admin's too, gets the anonymous answer:
    it must not learn that other depots' vehicles exist."""
    scheme, _, token = request.headers.get("authorization", "").partition(" ")
    token = token.strip()
    wanted = rt.api.metrics_token
    if (
        scheme.lower() == "bearer"
        and wanted
        and hmac.compare_digest(token.encode(), wanted.encode())
    ):
        return True
    try:
        resolved = await resolve_headers(rt, request.headers)
    except Exception:  # the database away: no details, the answer itself still counts
        return False
    if resolved is None:
        return False
    principal = resolved[0]
    return principal.allows("admin") and principal.acting_as("admin").scope.everything


@router.get(
    "/metrics",
    summary="Prometheus metrics (series naming buses and vehicles with the metrics token or "
    "a whole-fleet admin key only)",
    response_class=Response,
    responses={200: {"content": {"text/plain": {"schema": {"type": "string"}}}}},
)
async def metrics(request: Request, rt: Rt) -> Response:
    body: bytes = request.app.state.metrics.exposition(getattr(request.app.state, "alerts", None))
    if not await may_see_details(request, rt):
        body = b"\n".join(line for line in body.split(b"\n") if not _NAMING_LABELS.search(line))
    return Response(body, media_type=CONTENT_TYPE_LATEST)
