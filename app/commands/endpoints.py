"""Write endpoints: control commands, parameter writes and requests, and the command queue."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Depends, Header, Query

from eqgw.commands import repository as q
from eqgw.commands.model import (
    CommandKind,
    Json,
    command_target,
    describe_reach,
    public_command,
)
from eqgw.commands.schemas import CommandOut, ControlCommand, DeviceRequest, ParameterWrite
from eqgw.commands.validation import CommandRefused, Submitter
from eqgw.security.auth import OperatorWrite, Viewer, in_scope, scope_filter
from eqgw.security.keys import Principal
from eqgw.web.errors import ApiError
from eqgw.web.responses import JsonResponse
from eqgw.web.runtime import Rt, Runtime
from eqgw.web.schemas import errors

router = APIRouter(tags=["commands"], responses=errors(401, 403))

# 400: a body that is not JSON at all (FastAPI cannot parse it to validate it).
_WRITE = errors(400, 404, 409, 422, 429)
_IDEM = Header(
    default=None,
    alias="Idempotency-Key",
    max_length=200,
    description="A retried POST with the same key returns the same command",
)


async def _submit(
    rt: Runtime,
    who: Principal,
    kind: CommandKind,
    vehicle_id: str,
    body: dict[str, Json],
    idem: str | None,
) -> JsonResponse:
    action = f"command.{kind}"

    async def charge() -> None:
        await rt.check_write_rate(who, action, vehicle_id=vehicle_id, request=body)

    try:
        cmd, created = await rt.commands.submit(
            kind, vehicle_id, body, Submitter(who.key_id, who.name), idem, charge=charge
        )
    except CommandRefused as exc:
        await rt.audit(
            who,
            action,
            outcome="refused",
            status=exc.status,
            detail=exc.detail,
            vehicle_id=vehicle_id,
            request=body,
        )
        raise ApiError(exc.status, exc.detail, exc.type, extra=exc.extra) from exc
    await rt.audit(
        who,
        action,
        outcome="accepted" if created else "replayed",
        status=202,
        vehicle_id=vehicle_id,
        target=command_target(cmd),
        request=body,
        command_id=cmd.id,
        detail=describe_reach(cmd),
    )
    return JsonResponse(public_command(cmd), status_code=202)


@router.post(
    "/vehicles/{vehicle_id}/commands",
    status_code=202,
    response_model=CommandOut,
    responses=_WRITE,
    summary="Control the units of a bus (jump-start override, CAN on/off, equalizer on/off, "
    "Smart Sensor): a broadcast",
)
async def post_control(
    *,
    body: ControlCommand,
    idem: str | None = _IDEM,
    who: OperatorWrite,
    vehicle_id: Annotated[str, Depends(in_scope("command.control"))],
    rt: Rt,
) -> JsonResponse:
    return await _submit(
        rt, who, CommandKind.CONTROL, vehicle_id, body.model_dump(exclude_none=True), idem
    )


@router.post(
    "/vehicles/{vehicle_id}/parameters",
    status_code=202,
    response_model=CommandOut,
    responses=_WRITE,
    summary="Write parameters by name (a broadcast to the units of a bus), validated against "
    "the manuals' ranges and every unit's series",
)
async def post_parameters(
    *,
    body: ParameterWrite,
    idem: str | None = _IDEM,
    who: OperatorWrite,
    vehicle_id: Annotated[str, Depends(in_scope("command.parameters"))],
    rt: Rt,
) -> JsonResponse:
    return await _submit(
        rt, who, CommandKind.PARAMETERS, vehicle_id, body.model_dump(exclude_none=True), idem
    )


@router.post(
    "/vehicles/{vehicle_id}/requests",
    status_code=202,
    response_model=CommandOut,
    responses=_WRITE,
    summary="Ask the unit for DM1, component ID or software ID",
)
async def post_request(
    *,
    body: DeviceRequest,
    idem: str | None = _IDEM,
    who: OperatorWrite,
    vehicle_id: Annotated[str, Depends(in_scope("command.request"))],
    rt: Rt,
) -> JsonResponse:
    return await _submit(
        rt, who, CommandKind.REQUEST, vehicle_id, body.model_dump(exclude_none=True), idem
    )


@router.get(
    "/commands/{command_id}",
    response_model=CommandOut,
    responses=errors(404),
    summary="One command's life",
)
async def get_command(
    command_id: str,
    _who: Viewer,
    rt: Rt,
) -> JsonResponse:
    row = await rt.db(q.get_command, command_id)
    if row is None or not _who.sees(row.vehicle_id):
        raise _unknown_command(command_id)
    return JsonResponse(public_command(row))


def _unknown_command(command_id: str) -> ApiError:
    return ApiError(404, f"no command {command_id}", "unknown_command")


@router.get("/commands", response_model=list[CommandOut], summary="Recent commands")
async def list_commands(
    *,
    vehicle: str | None = Query(default=None, max_length=64),
    state: str | None = Query(default=None, max_length=16),
    limit: int = Query(default=100, ge=1, le=1000),
    _who: Viewer,
    rt: Rt,
) -> JsonResponse:
    rows = await rt.db(
        q.list_commands,
        vehicle_id=vehicle,
        states=[state] if state else None,
        vehicle_ids=scope_filter(_who),
        limit=limit,
    )
    return JsonResponse([public_command(r) for r in rows])


@router.delete(
    "/commands/{command_id}",
    response_model=CommandOut,
    responses=errors(404, 409, 429),
    summary="Cancel a pending command",
)
async def cancel_command(
    command_id: str,
    who: OperatorWrite,
    rt: Rt,
) -> JsonResponse:
    await rt.check_write_rate(who, "command.cancel", target=command_id)
    if not who.scope.everything:
        row = await rt.db(q.get_command, command_id)
        if row is None or not who.sees(row.vehicle_id):
            await rt.audit(
                who,
                "command.cancel",
                outcome="refused",
                status=404,
                detail="no such command in the key's scope",
                command_id=command_id,
            )
            raise _unknown_command(command_id)
    try:
        row = await rt.commands.cancel(command_id, Submitter(who.key_id, who.name))
    except CommandRefused as exc:
        await rt.audit(
            who,
            "command.cancel",
            outcome="refused",
            status=exc.status,
            detail=exc.detail,
            command_id=command_id,
        )
        raise ApiError(exc.status, exc.detail, exc.type) from exc
    await rt.audit(
        who,
        "command.cancel",
        outcome="accepted",
        status=200,
        vehicle_id=row.vehicle_id,
        command_id=command_id,
    )
    return JsonResponse(public_command(row))
