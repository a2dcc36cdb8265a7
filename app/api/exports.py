"""CSV exports for the whole fleet or a depot, any range, streamed: fault episodes, alerts and
the audit log.

`GET /faults`, `/alerts` and `/audit` answer the same CSV with `?format=csv` or
`Accept: text/csv` (and `/vehicles/{id}/history` its time series); these operations answer
CSV only, so that a client generated from the
OpenAPI document (which reads a route's answer by the first media type it declares, JSON for
those three) gets the export as text instead of failing to parse it as JSON.
"""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter, Query, Request
from fastapi.responses import Response, StreamingResponse

from eqgw.alerts.endpoints import alert_filters, alerts_csv
from eqgw.fleet.endpoints import faults_csv, vehicle_history
from eqgw.security.auth import OperatorRead, VehicleId, Viewer, vehicles_of
from eqgw.security.endpoints import audit_csv
from eqgw.web import csv_export
from eqgw.web.runtime import Rt
from eqgw.web.schemas import MAX_ID
from eqgw.web.times import time_filter


class CsvResponse(StreamingResponse):
    """A streamed `text/csv` answer (the class gives the OpenAPI document its media type)."""

    media_type = csv_export.MEDIA_TYPE


def _json_errors(*codes: int) -> dict[int | str, dict[str, Any]]:
    """Error answers, JSON (`errors()` would document them in the routes' media type, CSV)."""
    schema = {"schema": {"$ref": "#/components/schemas/ErrorBody"}}
    return {c: {"description": "Error", "content": {"application/json": schema}} for c in codes}


router = APIRouter(
    prefix="/exports",
    tags=["exports"],
    responses=_json_errors(401, 403, 422),
    default_response_class=CsvResponse,
)
_CSV: dict[int | str, dict[str, Any]] = {
    200: {"description": "CSV, a header line then a row each", "content": csv_export.CSV_CONTENT}
}
_FROM = Query(default=None, alias="from", description="Epoch s or ISO 8601")
_TO = Query(default=None, description="Epoch s or ISO 8601")
_VEHICLE = Query(default=None, max_length=64)
_DEPOT = Query(default=None, max_length=200, description="the fleet file's depot")


@router.get("/faults", responses=_CSV, summary="Fault episodes as CSV, fleet-wide or of a depot")
async def export_faults(
    *,
    from_: str | None = _FROM,
    to: str | None = _TO,
    vehicle: str | None = _VEHICLE,
    depot: str | None = _DEPOT,
    code: str | None = Query(default=None, max_length=64, description="e.g. OVF, IMB"),
    active: bool = False,
    who: Viewer,
    rt: Rt,
) -> StreamingResponse:
    """Every fault episode overlapping the range, with the unit's occurrence count, in the
    order they were recorded."""
    start, end = time_filter(from_, to)
    filters = {"vehicle_id": vehicle, "start": start, "end": end, "fault": code}
    return faults_csv(rt, vehicles_of(rt, who, depot), open_only=active, **filters)


@router.get("/alerts", responses=_CSV, summary="Alerts as CSV, fleet-wide or of a depot")
async def export_alerts(
    *,
    from_: str | None = Query(default=None, alias="from", description="open at or after"),
    to: str | None = Query(default=None, description="raised at or before"),
    vehicle: str | None = _VEHICLE,
    depot: str | None = _DEPOT,
    state: str | None = Query(default=None, description="active, acknowledged, cleared, open"),
    severity: str | None = Query(default=None, description="comma-separated"),
    rule: str | None = Query(default=None, max_length=2000, description="comma-separated"),
    muted: bool | None = None,
    who: Viewer,
    rt: Rt,
) -> StreamingResponse:
    """Every alert open at some time in the range, oldest first."""
    filters = alert_filters(vehicle, state, severity, rule, muted, from_, to)
    return alerts_csv(rt, vehicles_of(rt, who, depot), **filters)


@router.get("/audit", responses=_CSV, summary="The audit log as CSV, fleet-wide or of a depot")
async def export_audit(
    *,
    from_: str | None = _FROM,
    to: str | None = _TO,
    vehicle: str | None = _VEHICLE,
    depot: str | None = _DEPOT,
    key_id: int | None = Query(default=None, ge=1, le=MAX_ID),
    who: OperatorRead,
    rt: Rt,
) -> StreamingResponse:
    """Every audit entry in the range, oldest first (operators and admins; a scoped key gets
    the entries of its vehicles only)."""
    start, end = time_filter(from_, to)
    filters = {"start": start, "end": end, "vehicle_id": vehicle, "key_id": key_id}
    return audit_csv(rt, vehicles_of(rt, who, depot), **filters)


@router.get(
    "/vehicles/{vehicle_id}/history",
    responses={**_CSV, **_json_errors(404)},
    summary="Time series of one unit as CSV",
)
async def export_vehicle_history(
    *,
    request: Request,
    from_: str | None = Query(default=None, alias="from", description="Epoch s or ISO 8601"),
    to: str | None = Query(default=None, description="Epoch s or ISO 8601 (default now)"),
    bucket: str = Query(default="auto", description="raw, 1m, 15m, 1h, 1d or auto"),
    fields: str = Query(default="v12,v24", description="Comma-separated metrics"),
    unit: int | None = Query(default=None, ge=0, le=253),
    who: Viewer,
    rt: Rt,
    vehicle_id: VehicleId,
) -> Response:
    """`GET /vehicles/{id}/history?format=csv`, with the same limits."""
    return await vehicle_history(
        request=request,
        vehicle_id=vehicle_id,
        from_=from_,
        to=to,
        bucket=bucket,
        fields=fields,
        unit=unit,
        format="csv",
        rt=rt,
        who=who,
    )
