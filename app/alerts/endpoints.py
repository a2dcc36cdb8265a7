"""Alert endpoints: list and acknowledge alerts (operators), rules and mutes (admins)."""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any, Concatenate

from fastapi import APIRouter, Path, Query, Request
from fastapi.responses import Response, StreamingResponse
from sqlalchemy import Connection

from eqgw.alerts import repository as aq
from eqgw.alerts.engine import AlertEngine
from eqgw.alerts.rules import CONDITIONS, validate_rule
from eqgw.alerts.schemas import (
    MAX_MUTE_S,
    Acknowledge,
    AlertDetail,
    AlertList,
    AlertOut,
    MuteIn,
    MuteList,
    MuteOut,
    RuleIn,
    RuleList,
    RuleOut,
    RulePatch,
)
from eqgw.ingest import events
from eqgw.ingest.events import Event, UnitRef
from eqgw.security.auth import (
    AdminWrite,
    OperatorWrite,
    Viewer,
    scope_filter,
    unknown_vehicle,
    vehicles_of,
)
from eqgw.security.keys import Principal
from eqgw.store.queries import list_vehicles
from eqgw.store.transaction import P, R, run_in_transaction
from eqgw.web import csv_export
from eqgw.web.errors import ApiError
from eqgw.web.responses import JsonResponse
from eqgw.web.runtime import Rt, Runtime
from eqgw.web.schemas import MAX_ID, errors
from eqgw.web.times import parse_time

router = APIRouter(tags=["alerts"], responses=errors(401, 403))

_STATE_DOC = "active, acknowledged, cleared or open (active and acknowledged), comma-separated"
_STATE = r"\s*(active|acknowledged|cleared|open)?\s*"
_STATES = rf"^{_STATE}(,{_STATE})*$"
_RULE_ID = Path(pattern=r"^[a-z0-9][a-z0-9_.-]{0,63}$")


async def _write(
    rt: Runtime, fn: Callable[Concatenate[Connection, P], R], /, *args: P.args, **kwargs: P.kwargs
) -> R:
    """A store change in one transaction holding SQLite's write lock from the start."""
    db = rt.engine.execution_options(sqlite_begin="IMMEDIATE")
    return await run_in_transaction(db, fn, *args, **kwargs)


def _engine(request: Request) -> AlertEngine | None:
    engine: AlertEngine | None = getattr(request.app.state, "alerts", None)
    return engine


def _csv(value: str | None, allowed: tuple[str, ...] | None, name: str) -> list[str] | None:
    if not value:
        return None
    items = [v.strip() for v in value.split(",") if v.strip()]
    if allowed is not None:
        bad = [v for v in items if v not in allowed]
        if bad:
            raise ApiError(422, f"{name}: {', '.join(bad)} unknown; use {', '.join(allowed)}")
    return items


# -- rules (before /alerts/{id}: "rules" is not an id) -----------------------------------


def _kinds() -> dict[str, dict[str, Any]]:
    return {
        k: {"params": list(c.required), "description": c.description}
        for k, c in sorted(CONDITIONS.items())
    }


@router.get("/alerts/rules", response_model=RuleList)
async def get_rules(
    _who: Viewer,
    rt: Rt,
) -> JsonResponse:
    """Every alert rule, and the condition kinds a rule can use."""
    return JsonResponse({"rules": await rt.db(aq.list_rules), "kinds": _kinds()})


@router.get("/alerts/rules/{rule_id}", response_model=RuleOut, responses=errors(404, 422))
async def get_rule(
    *,
    rule_id: str = _RULE_ID,
    _who: Viewer,
    rt: Rt,
) -> JsonResponse:
    row = await rt.db(aq.get_rule, rule_id)
    if row is None:
        raise ApiError(404, f"no alert rule {rule_id!r}", "unknown_rule")
    return JsonResponse(row)


async def _refused(
    who: Principal,
    rt: Runtime,
    action: str,
    status: int,
    detail: str,
    target: str,
    request: dict[str, Any] | None = None,
    type_: str | None = None,
) -> ApiError:
    await rt.audit(
        who, action, outcome="refused", status=status, detail=detail, target=target, request=request
    )
    return ApiError(status, detail, type_)


async def _fleet_wide(
    who: Principal, rt: Runtime, action: str, target: str, request: dict[str, Any] | None = None
) -> None:
    """Rules apply to every vehicle: a key scoped to some depots or vehicles may read them
    but not change them (403)."""
    if not who.scope.everything:
        raise await _refused(
            who,
            rt,
            action,
            403,
            "alert rules apply to the whole fleet: only a key of the whole fleet may change them",
            target,
            request,
            "out_of_scope",
        )


@router.post(
    "/alerts/rules", status_code=201, response_model=RuleOut, responses=errors(400, 409, 422, 429)
)
async def post_rule(
    body: RuleIn,
    request: Request,
    who: AdminWrite,
    rt: Rt,
) -> JsonResponse:
    """Create a rule (admins)."""
    req = body.model_dump()
    target = f"rule {body.id}"
    await _fleet_wide(who, rt, "alert_rule.create", target, req)
    await rt.check_write_rate(who, "alert_rule.create", target=target, request=req)
    problems = validate_rule(body.kind, body.severity, body.params)
    if problems:
        raise await _refused(who, rt, "alert_rule.create", 422, "; ".join(problems), target, req)
    row = {**req, "source": "api"}
    if not await _write(rt, aq.insert_rule, row, time.time()):
        raise await _refused(
            who, rt, "alert_rule.create", 409, f"alert rule {body.id!r} exists", target, req
        )
    await rt.audit(
        who, "alert_rule.create", outcome="accepted", status=201, target=target, request=req
    )
    await _rules_changed(request)
    return JsonResponse(await rt.db(aq.get_rule, body.id), status_code=201)


@router.patch(
    "/alerts/rules/{rule_id}", response_model=RuleOut, responses=errors(400, 404, 422, 429)
)
async def patch_rule(
    *,
    body: RulePatch,
    request: Request,
    rule_id: str = _RULE_ID,
    who: AdminWrite,
    rt: Rt,
) -> JsonResponse:
    """Change a rule (admins): severity, enabled, params (merged), targets, description. A
    built-in or config-file rule changed here keeps the change across restarts."""
    req = body.model_dump(exclude_unset=True)
    target = f"rule {rule_id}"
    await _fleet_wide(who, rt, "alert_rule.update", target, req)
    await rt.check_write_rate(who, "alert_rule.update", target=target, request=req)
    row = await rt.db(aq.get_rule, rule_id)
    if row is None:
        raise await _refused(
            who, rt, "alert_rule.update", 404, f"no alert rule {rule_id!r}", target, req
        )
    values: dict[str, Any] = {k: v for k, v in req.items() if v is not None or k == "description"}
    if "params" in values:
        values["params"] = {**row["params"], **values["params"]}
    problems = validate_rule(
        row["kind"], values.get("severity", row["severity"]), values.get("params", row["params"])
    )
    if problems:
        raise await _refused(who, rt, "alert_rule.update", 422, "; ".join(problems), target, req)
    await _write(rt, aq.update_rule, rule_id, {**values, "source": "api"}, time.time())
    await rt.audit(
        who, "alert_rule.update", outcome="accepted", status=200, target=target, request=req
    )
    await _rules_changed(request)
    return JsonResponse(await rt.db(aq.get_rule, rule_id))


@router.delete(
    "/alerts/rules/{rule_id}", response_model=RuleOut, responses=errors(404, 409, 422, 429)
)
async def delete_rule(
    *,
    request: Request,
    rule_id: str = _RULE_ID,
    who: AdminWrite,
    rt: Rt,
) -> JsonResponse:
    """Delete a rule (admins); its open alerts are cleared. Built-in and config-file rules
    come back at the next start: disable them instead (409)."""
    target = f"rule {rule_id}"
    await _fleet_wide(who, rt, "alert_rule.delete", target)
    await rt.check_write_rate(who, "alert_rule.delete", target=target)
    row = await rt.db(aq.get_rule, rule_id)
    if row is None:
        raise await _refused(
            who, rt, "alert_rule.delete", 404, f"no alert rule {rule_id!r}", target
        )
    configured = rule_id in _configured_rules(rt)
    if configured:
        raise await _refused(
            who,
            rt,
            "alert_rule.delete",
            409,
            f"{rule_id} is a built-in or config-file rule; disable it instead "
            '(PATCH {"enabled": false})',
            target,
        )
    await _write(rt, aq.delete_rule, rule_id)
    await rt.audit(who, "alert_rule.delete", outcome="accepted", status=200, target=target)
    await _rules_changed(request)
    return JsonResponse(row)


def _configured_rules(rt: Runtime) -> set[str]:
    from eqgw.alerts.config import resolve_rules

    return set(resolve_rules(rt.settings.alerts))


async def _rules_changed(request: Request) -> None:
    engine = _engine(request)
    if engine is not None:
        await engine.rules_changed()


# -- mutes ----------------------------------------------------------------------------------


def _hhmm(value: str) -> int:
    h, m = value.split(":")
    return int(h) * 60 + int(m)


def _mute_out(row: dict[str, Any], now: float) -> dict[str, Any]:
    lo, hi = row.pop("daily_from_min"), row.pop("daily_to_min")
    row["quiet_hours"] = (
        None
        if lo is None
        else {"from": f"{lo // 60:02d}:{lo % 60:02d}", "to": f"{hi // 60:02d}:{hi % 60:02d}"}
    )
    row["active"] = row["cancelled_at"] is None and row["starts_at"] <= now < row["ends_at"]
    return row


@router.get("/alerts/mutes", response_model=MuteList)
async def get_mutes(
    *,
    active: bool = Query(default=False, description="only mutes not cancelled or expired"),
    who: Viewer,
    rt: Rt,
) -> JsonResponse:
    """Mutes, newest first (a scoped key: those of its vehicles, and fleet-wide ones)."""
    now = time.time()
    rows = await rt.db(
        aq.list_mutes, active_at=now if active else None, vehicle_ids=scope_filter(who)
    )
    return JsonResponse({"mutes": [_mute_out(r, now) for r in rows]})


@router.post(
    "/alerts/mutes", status_code=201, response_model=MuteOut, responses=errors(400, 404, 422, 429)
)
async def post_mute(
    body: MuteIn,
    who: AdminWrite,
    rt: Rt,
) -> JsonResponse:
    """Mute alerts of a vehicle (or all) and a rule (or all) until an expiry (admins): they
    are still recorded, marked muted, and not delivered."""
    now = time.time()
    req = body.model_dump(by_alias=True, exclude_unset=True)
    target = f"mute {body.vehicle_id or '*'}/{body.rule or '*'}"
    if body.vehicle_id is None:
        await _fleet_wide(who, rt, "alert_mute.create", target, req)
    elif not who.sees(body.vehicle_id):
        await rt.audit(
            who,
            "alert_mute.create",
            outcome="refused",
            status=404,
            target=target,
            detail="outside the key's scope",
            request=req,
        )
        raise unknown_vehicle(body.vehicle_id)
    await rt.check_write_rate(who, "alert_mute.create", target=target, request=req)
    starts = body.starts_at if body.starts_at is not None else now
    if (body.ends_at is None) == (body.duration_s is None):
        raise await _refused(
            who,
            rt,
            "alert_mute.create",
            422,
            "give exactly one of ends_at and duration_s",
            target,
            req,
        )
    ends = body.ends_at if body.ends_at is not None else starts + (body.duration_s or 0)
    problem = None
    if ends <= starts or ends <= now:
        problem = "the mute must end after it starts and in the future"
    elif ends - starts > MAX_MUTE_S:
        problem = f"a mute lasts at most {MAX_MUTE_S // 86400} days"
    elif body.quiet_hours is not None and body.quiet_hours.start == body.quiet_hours.end:
        problem = "quiet hours need a window (from and to differ)"
    if problem:
        raise await _refused(who, rt, "alert_mute.create", 422, problem, target, req)
    if body.vehicle_id is not None:
        known = {v["id"] for v in await rt.db(list_vehicles)}
        if body.vehicle_id not in known:
            raise await _refused(
                who, rt, "alert_mute.create", 404, f"no vehicle {body.vehicle_id!r}", target, req
            )
    if body.rule is not None and await rt.db(aq.get_rule, body.rule) is None:
        raise await _refused(
            who, rt, "alert_mute.create", 404, f"no alert rule {body.rule!r}", target, req
        )
    qh = body.quiet_hours
    row = await _write(
        rt,
        aq.insert_mute,
        {
            "vehicle_id": body.vehicle_id,
            "rule": body.rule,
            "starts_at": starts,
            "ends_at": ends,
            "daily_from_min": _hhmm(qh.start) if qh else None,
            "daily_to_min": _hhmm(qh.end) if qh else None,
            "reason": body.reason,
            "created_by": who.name,
        },
        now,
    )
    await rt.audit(
        who,
        "alert_mute.create",
        outcome="accepted",
        status=201,
        target=f"mute {row['id']}",
        request=req,
        vehicle_id=body.vehicle_id,
    )
    return JsonResponse(_mute_out(row, now), status_code=201)


@router.delete("/alerts/mutes/{mute_id}", response_model=MuteOut, responses=errors(404, 422, 429))
async def delete_mute(
    *,
    mute_id: int = Path(ge=1, le=MAX_ID),
    who: AdminWrite,
    rt: Rt,
) -> JsonResponse:
    """End a mute now (admins)."""
    await rt.check_write_rate(who, "alert_mute.cancel", target=f"mute {mute_id}")
    now = time.time()
    mute = await rt.db(aq.get_mute, mute_id)
    if (
        mute is None
        or not who.sees(mute["vehicle_id"])
        or not await _write(rt, aq.cancel_mute, mute_id, now)
    ):
        raise await _refused(
            who, rt, "alert_mute.cancel", 404, f"no active mute {mute_id}", f"mute {mute_id}"
        )
    await rt.audit(
        who, "alert_mute.cancel", outcome="accepted", status=200, target=f"mute {mute_id}"
    )
    mute = await rt.db(aq.get_mute, mute_id)
    if mute is None:  # deleted in between
        raise ApiError(404, f"no mute {mute_id}", "unknown_mute")
    return JsonResponse(_mute_out(mute, now))


# -- alerts ---------------------------------------------------------------------------------


@router.get(
    "/alerts",
    response_model=AlertList,
    responses={**errors(422), 200: {"content": csv_export.CSV_CONTENT}},
)
async def get_alerts(
    *,
    request: Request,
    vehicle: str | None = Query(default=None, max_length=64),
    depot: str | None = Query(default=None, max_length=200, description="the fleet file's depot"),
    state: str | None = Query(
        default=None, description=_STATE_DOC, json_schema_extra={"pattern": _STATES}
    ),
    severity: str | None = Query(default=None, description="comma-separated"),
    rule: str | None = Query(default=None, max_length=2000, description="comma-separated"),
    muted: bool | None = None,
    from_: str | None = Query(default=None, alias="from", description="open at or after"),
    to: str | None = Query(default=None, description="raised at or before"),
    before: int | None = Query(default=None, ge=1, le=MAX_ID, description="ids below (paging)"),
    limit: int = Query(default=100, ge=1, le=1000),
    format: str | None = Query(
        default=None,
        pattern="^(json|csv)$",
        description="json (default), or csv: every alert that matches, oldest first, streamed "
        "(`limit` does not apply), as `Accept: text/csv` asks",
    ),
    who: Viewer,
    rt: Rt,
) -> Response:
    """Alerts, newest first, filtered by vehicle, depot, state, severity, rule, muted and time;
    or as CSV, all of them at once."""
    filters = alert_filters(vehicle, state, severity, rule, muted, from_, to, before)
    vehicle_ids = vehicles_of(rt, who, depot)
    if csv_export.wants_csv(request, format):
        return alerts_csv(rt, vehicle_ids, **filters)
    rows = await rt.db(aq.list_alerts, **filters, limit=limit, vehicle_ids=vehicle_ids)
    return JsonResponse({"alerts": rows})


def alert_filters(
    vehicle: str | None,
    state: str | None,
    severity: str | None,
    rule: str | None,
    muted: bool | None,
    from_: str | None,
    to: str | None,
    before: int | None = None,
) -> dict[str, Any]:
    """The keyword arguments of `aq.list_alerts` for the query parameters (checked)."""
    states = _csv(state, (*aq.STATES, "open"), "state")
    if states and "open" in states:
        states = [s for s in states if s != "open"] + [aq.ACTIVE, aq.ACKNOWLEDGED]
    return {
        "vehicle_id": vehicle,
        "states": states,
        "severities": _csv(severity, ("info", "warning", "critical"), "severity"),
        "rules": _csv(rule, None, "rule"),
        # Not a window: open at or after `from` and raised at or before `to` may have
        # `from` after `to` (alerts that lasted across both), so no order is checked.
        "start": parse_time(from_, 0.0, "from") if from_ else None,
        "end": parse_time(to, 0.0, "to") if to else None,
        "muted": muted,
        "before_id": before,
    }


@router.get("/alerts/{alert_id}", response_model=AlertDetail, responses=errors(404, 422))
async def get_alert(
    *,
    alert_id: int = Path(ge=1, le=MAX_ID),
    who: Viewer,
    rt: Rt,
) -> JsonResponse:
    """One alert with its history (every raised/acknowledged/cleared event)."""

    def load(conn: Any) -> dict[str, Any] | None:
        alert = aq.get_alert(conn, alert_id)
        return None if alert is None else {**alert, "events": aq.alert_events(conn, alert_id)}

    detail = await rt.db(load)
    if detail is None or not who.sees(detail["vehicle_id"]):
        raise ApiError(404, f"no alert {alert_id}", "unknown_alert")
    return JsonResponse(detail)


@router.post(
    "/alerts/{alert_id}/acknowledge",
    response_model=AlertOut,
    responses=errors(400, 404, 409, 422, 429),
)
async def acknowledge(
    *,
    body: Acknowledge,
    alert_id: int = Path(ge=1, le=MAX_ID),
    who: OperatorWrite,
    rt: Rt,
) -> JsonResponse:
    """Acknowledge an active alert (operators and admins), with an optional comment."""
    now = time.time()
    target = f"alert {alert_id}"
    await rt.check_write_rate(who, "alert.acknowledge", target=target, request=body.model_dump())
    if not who.scope.everything:
        found = await rt.db(aq.get_alert, alert_id)
        if found is None or not who.sees(found["vehicle_id"]):
            raise await _refused(who, rt, "alert.acknowledge", 404, f"no alert {alert_id}", target)
    try:
        alert = await _write(
            rt, aq.acknowledge_alert, alert_id, by=who.name, comment=body.comment, ts=now
        )
    except aq.AlertStateError as exc:
        raise await _refused(who, rt, "alert.acknowledge", 409, str(exc), target) from exc
    if alert is None:
        raise await _refused(who, rt, "alert.acknowledge", 404, f"no alert {alert_id}", target)
    await rt.audit(
        who,
        "alert.acknowledge",
        outcome="accepted",
        status=200,
        target=target,
        vehicle_id=alert["vehicle_id"],
        request=body.model_dump(),
    )
    ref = UnitRef(alert["vehicle_id"], alert["bus"], alert["sa"])
    rt.ingest.hub.publish(Event(events.ALERT_ACKNOWLEDGED, ref, now, alert))
    return JsonResponse(alert)


ALERT_COLUMNS = (
    "id",
    "vehicle_id",
    "vehicle_name",
    "bus",
    "sa",
    "rule",
    "severity",
    "state",
    "muted",
    "message",
    "raised_at",
    "acknowledged_at",
    "acknowledged_by",
    "ack_comment",
    "cleared_at",
    "values",
)


def alerts_csv(rt: Runtime, vehicle_ids: list[str] | None, **filters: Any) -> StreamingResponse:
    """Alerts (`aq.list_alerts` filters), oldest first."""

    def page(conn: Connection, after: int, limit: int) -> list[dict[str, Any]]:
        return aq.list_alerts(conn, vehicle_ids=vehicle_ids, after_id=after, limit=limit, **filters)

    return csv_export.stream(rt, "alerts", ALERT_COLUMNS, page)
