"""The fleet's management routes: vehicles and their buses created, changed, deleted and
imported from CSV by admins, without a restart (every gateway follows: eqgw.fleet.sync).

A scoped admin manages the vehicles of its depots (or its vehicles) only: another depot's
vehicle is answered as one that does not exist, and creating a vehicle in another depot, or
moving one there, is a 403. Vehicle ids and bus names are unique in the whole fleet, so a
create that takes an id in use is a 409 whoever holds it. Every change is audited in the
transaction that makes it; every refusal after the key check is audited too.
"""

from __future__ import annotations

import asyncio
from typing import Annotated, Any, Literal

from fastapi import APIRouter, Depends, Query, Request
from pydantic import ValidationError
from sqlalchemy import Connection

from eqgw.bus.config import BusConfig
from eqgw.config import VehicleConfig
from eqgw.fleet import importer, registry
from eqgw.fleet.registry import Edit, Fleet, Outcome, Problem, VehicleSpec, may_manage
from eqgw.fleet.schemas import (
    BusIn,
    BusOut,
    ImportRefused,
    ImportReport,
    VehicleCreate,
    VehicleOut,
    VehiclePatch,
)
from eqgw.security import repository as q
from eqgw.security.audit import audit_entry
from eqgw.security.auth import AdminRead, AdminWrite, VehicleId, in_scope, unknown_vehicle
from eqgw.security.keys import Principal
from eqgw.store.engine import health_of, unavailable_error
from eqgw.web.errors import ApiError
from eqgw.web.responses import JsonResponse
from eqgw.web.runtime import Rt, Runtime
from eqgw.web.schemas import bad_text, errors

router = APIRouter(tags=["fleet"], responses=errors(401, 403))

_TYPES = {403: "out_of_scope", 404: "unknown_vehicle", 409: "conflict", 422: "invalid_vehicle"}
CSV_TYPES = ("text/csv", "text/plain", "application/csv")
# A route's vehicle within the caller's scope; a refusal audited under the route's action.
UpdatedVehicle = Annotated[str, Depends(in_scope("vehicle.update"))]
DeletedVehicle = Annotated[str, Depends(in_scope("vehicle.delete"))]


def bus_out(bus: BusConfig) -> dict[str, Any]:
    row = registry.bus_row(bus)
    return BusOut.model_validate(row).model_dump()


def vehicle_out(fleet: Fleet, vehicle_id: str) -> dict[str, Any]:
    v = fleet.vehicles[vehicle_id]
    buses = sorted(fleet.buses_of(vehicle_id), key=lambda b: b.name)
    return {
        "id": v.id,
        "name": v.display_name,
        "depot": v.depot,
        "buses": [bus_out(b) for b in buses],
        "version": fleet.version,
    }


def _buses(vehicle_id: str, given: list[BusIn]) -> tuple[list[BusConfig], list[Problem]]:
    """A body's buses as the vehicle's (checked again as BusConfig: the fleet file's check)."""
    out: list[BusConfig] = []
    problems = []
    for i, bus in enumerate(given):
        if bus.vehicle_id not in (None, vehicle_id):
            problems.append(
                Problem(
                    f"buses.{i}.vehicle_id: {bus.vehicle_id!r} is not this vehicle",
                    vehicle_id=vehicle_id,
                )
            )
            continue
        values = bus.model_dump(exclude={"vehicle_id"}, exclude_unset=True)
        try:
            out.append(BusConfig.model_validate({**values, "vehicle_id": vehicle_id}))
        except ValidationError as exc:
            problems.append(Problem(f"buses.{i}: {registry.reasons(exc)}", vehicle_id=vehicle_id))
    return out, problems


async def _change(
    rt: Runtime,
    who: Principal,
    action: str,
    edit: Edit | Any,
    *,
    mode: registry.Mode,
    vehicle_id: str | None,
    request: dict[str, Any] | None,
    dry_run: bool = False,
) -> Outcome:
    """Make the change (one transaction, audited in it); a refusal is audited and raised as
    the caller answers it."""
    if health_of(rt.engine).down():
        raise unavailable_error()
    target = f"vehicle {vehicle_id}" if vehicle_id else "fleet"

    def audit(conn: Connection, outcome: Outcome) -> None:
        if mode in ("merge", "replace"):
            for c in outcome.changes:
                if c.kind in ("added", "changed", "removed"):
                    detail = c.kind + (f": {', '.join(c.fields)}" if c.fields else "")
                    q.add_audit(
                        conn,
                        audit_entry(
                            who,
                            action,
                            outcome="accepted",
                            status=200,
                            detail=detail,
                            vehicle_id=c.vehicle_id,
                            target=f"vehicle {c.vehicle_id}",
                            request={"line": c.line, "mode": mode},
                        ),
                    )
        q.add_audit(
            conn,
            audit_entry(
                who,
                action,
                outcome="accepted",
                status=201 if mode == "create" else 200,
                detail=outcome.summary(),
                vehicle_id=vehicle_id,
                target=target,
                request=request,
            ),
        )

    outcome: Outcome = await asyncio.to_thread(
        registry.change,
        rt.engine,
        edit,
        mode=mode,
        scope=who.scope,
        dry_run=dry_run,
        origin="the API",
        audit=audit,
    )
    if outcome.problems and not dry_run:
        await rt.audit(
            who,
            action,
            outcome="refused",
            status=outcome.status,
            detail=outcome.summary(),
            vehicle_id=vehicle_id,
            target=target,
            request=request,
        )
    if outcome.applied and rt.fleet_sync is not None:
        await rt.fleet_sync.changed(outcome.version)
    return outcome


def _refusal(outcome: Outcome) -> ApiError:
    status = outcome.status
    if status == 404:
        first = next(p for p in outcome.problems if p.status == 404)
        return unknown_vehicle(first.vehicle_id or "")
    return ApiError(status, outcome.summary(), _TYPES.get(status))


@router.post(
    "/vehicles",
    status_code=201,
    response_model=VehicleOut,
    responses=errors(400, 409, 422, 429),
    summary="Add a vehicle and its buses; every gateway opens them within seconds",
)
async def create_vehicle(body: VehicleCreate, who: AdminWrite, rt: Rt) -> JsonResponse:
    """Add a vehicle (a deleted one's id brings its history back). A scoped admin adds
    vehicles to its own depots only (403 for another)."""
    req = body.model_dump(mode="json", exclude_unset=True)
    await rt.check_write_rate(who, "vehicle.create", vehicle_id=body.id, request=req)
    buses, problems = _buses(body.id, body.buses)
    vehicle = VehicleConfig(id=body.id, name=body.name, depot=body.depot)
    edit = Edit([VehicleSpec(vehicle, buses)], problems=problems)
    outcome = await _change(
        rt, who, "vehicle.create", edit, mode="create", vehicle_id=body.id, request=req
    )
    if outcome.problems:
        raise _refusal(outcome)
    assert outcome.fleet is not None
    return JsonResponse(vehicle_out(outcome.fleet, body.id), status_code=201)


@router.get(
    "/vehicles/{vehicle_id}/config",
    response_model=VehicleOut,
    responses=errors(404),
    summary="A vehicle as the fleet holds it: name, depot and every bus's configuration",
)
async def get_vehicle_config(who: AdminRead, vehicle_id: VehicleId, rt: Rt) -> JsonResponse:
    fleet: Fleet = await rt.db(registry.load)
    v = fleet.vehicles.get(vehicle_id)
    if v is None or not may_manage(who.scope, vehicle_id, v.depot):
        raise unknown_vehicle(vehicle_id)
    return JsonResponse(vehicle_out(fleet, vehicle_id))


@router.patch(
    "/vehicles/{vehicle_id}",
    response_model=VehicleOut,
    responses=errors(400, 404, 409, 422, 429),
    summary="Change a vehicle: name, depot, buses (changed buses are reopened)",
)
async def update_vehicle(
    body: VehiclePatch, who: AdminWrite, vehicle_id: UpdatedVehicle, rt: Rt
) -> JsonResponse:
    """Change a vehicle; `buses`, when given, is its complete list. A scoped admin cannot
    move a vehicle to a depot outside its scope (403)."""
    req = body.model_dump(mode="json", exclude_unset=True)
    await rt.check_write_rate(who, "vehicle.update", vehicle_id=vehicle_id, request=req)
    given = body.model_fields_set

    def edit(fleet: Fleet) -> Edit:
        have = fleet.vehicles.get(vehicle_id)
        if have is None or not may_manage(who.scope, vehicle_id, have.depot):
            return Edit(problems=[Problem(f"no vehicle {vehicle_id!r}", 404, None, vehicle_id)])
        name = body.name if "name" in given else have.name
        depot = body.depot if "depot" in given else have.depot
        try:
            vehicle = VehicleConfig(id=vehicle_id, name=name, depot=depot)
        except ValidationError as exc:
            return Edit(problems=[Problem(registry.reasons(exc), vehicle_id=vehicle_id)])
        if body.buses is None:
            return Edit([VehicleSpec(vehicle, fleet.buses_of(vehicle_id))])
        buses, problems = _buses(vehicle_id, body.buses)
        return Edit([VehicleSpec(vehicle, buses)], problems=problems)

    outcome = await _change(
        rt, who, "vehicle.update", edit, mode="update", vehicle_id=vehicle_id, request=req
    )
    if outcome.problems:
        raise _refusal(outcome)
    assert outcome.fleet is not None
    return JsonResponse(vehicle_out(outcome.fleet, vehicle_id))


@router.delete(
    "/vehicles/{vehicle_id}",
    response_model=VehicleOut,
    responses=errors(404, 429),
    summary="Delete a vehicle: its buses are closed on every gateway; its history is kept",
)
async def delete_vehicle(who: AdminWrite, vehicle_id: DeletedVehicle, rt: Rt) -> JsonResponse:
    """Delete (retire) a vehicle: it leaves the fleet and its buses are closed; its history
    stays in the database (retention prunes it as any other), and creating its id again
    brings it back. The answer is the vehicle as it was."""
    await rt.check_write_rate(who, "vehicle.delete", vehicle_id=vehicle_id)
    before: dict[str, Any] = {}

    def edit(fleet: Fleet) -> Edit:
        if vehicle_id in fleet.vehicles:
            before.update(vehicle_out(fleet, vehicle_id))
        return Edit(remove=[vehicle_id])

    outcome = await _change(
        rt, who, "vehicle.delete", edit, mode="delete", vehicle_id=vehicle_id, request=None
    )
    if outcome.problems:
        raise _refusal(outcome)
    return JsonResponse({**before, "version": outcome.version})


@router.post(
    "/vehicles/import",
    response_model=ImportReport,
    responses={
        **errors(413, 415, 429),
        403: {"model": ImportRefused, "description": "a row outside the caller's scope"},
        422: {"model": ImportRefused, "description": "bad rows: nothing was changed"},
    },
    summary="Add, change (and with mode=replace remove) vehicles from a CSV file; dry_run "
    "lists what would change",
    openapi_extra={
        "requestBody": {
            "required": True,
            "description": "CSV, one row per bus: vehicle_id,name,depot,bus,interface,"
            "channel,bitrate,equalizer_sas,gateway_sa,... (see docs/api.md)",
            "content": {"text/csv": {"schema": {"type": "string"}}},
        }
    },
)
async def import_vehicles(
    request: Request,
    who: AdminWrite,
    rt: Rt,
    dry_run: bool = Query(default=False, description="list what would change; change nothing"),
    mode: Literal["merge", "replace"] = Query(
        default="merge",
        description="merge: vehicles the file leaves out are untouched; replace: they are "
        "deleted (those in the caller's scope)",
    ),
) -> JsonResponse:
    """Import vehicles and buses from CSV in one transaction: every bad row is listed with its
    line number and reason, and when there is any, nothing is changed. A vehicle in the file
    is set whole: its name, its depot and exactly the buses its rows give."""
    media = request.headers.get("content-type", "").split(";")[0].strip().lower()
    if media not in CSV_TYPES:
        raise ApiError(415, "send the CSV file as text/csv", "unsupported_media_type")
    try:
        text = (await request.body()).decode("utf-8")
    except UnicodeDecodeError as exc:
        raise ApiError(422, "the file is not UTF-8 text", "invalid_rows") from exc
    req = {"mode": mode, "dry_run": dry_run, "bytes": len(text)}
    reason = bad_text(text)
    if reason is not None:
        raise ApiError(422, reason, "invalid_rows")
    if not dry_run:
        await rt.check_write_rate(who, "vehicle.import", request=req)
    edit = importer.parse(text)
    outcome = await _change(
        rt,
        who,
        "vehicle.import",
        edit,
        mode=mode,
        vehicle_id=None,
        request=req,
        dry_run=dry_run,
    )
    if outcome.problems:
        status = 403 if outcome.status == 403 else 422
        raise ApiError(
            status,
            outcome.summary(),
            "out_of_scope" if status == 403 else "invalid_rows",
            extra=outcome.report(),
        )
    return JsonResponse(outcome.report())
