"""Read endpoints: the fleet, a vehicle's live values with diagnosis, history and faults."""

from __future__ import annotations

import asyncio
import csv
import io
import time
from collections.abc import Mapping, Sequence
from typing import Any

from fastapi import APIRouter, Depends, Query, Request
from fastapi.responses import Response, StreamingResponse
from sqlalchemy import Connection
from sqlalchemy.exc import InterfaceError, OperationalError
from sqlalchemy.exc import TimeoutError as PoolTimeout

from eqgw.fleet.diagnosis import Batteries, diagnose
from eqgw.fleet.schemas import (
    FaultList,
    History,
    StatusHistory,
    VehicleList,
    VehicleLive,
)
from eqgw.ingest.state import UnitState, vehicle_status
from eqgw.security.auth import VehicleId, Viewer, scope_filter, unknown_vehicle, vehicles_of, viewer
from eqgw.store import queries
from eqgw.web import csv_export
from eqgw.web.errors import ApiError
from eqgw.web.responses import JsonResponse, dumps
from eqgw.web.runtime import Rt, Runtime
from eqgw.web.schemas import errors
from eqgw.web.times import time_filter, time_window

router = APIRouter(tags=["fleet"], dependencies=[Depends(viewer)], responses=errors(401, 403))

_SOC_SLOTS = {"soc_12v": "battery_states/2", "soc_24v": "battery_states/4"}
_SOH_SLOTS = {"soh_12v": "battery_states/1", "soh_24v": "battery_states/3"}


def _fields(st: UnitState, slot: str) -> dict[str, Any]:
    hit = st.latest.get(slot)
    return hit[1] if hit else {}


def _online(st: UnitState) -> bool:
    return st.is_online()


def unit_summary(st: UnitState) -> dict[str, Any]:
    """One unit's live summary: online, voltages, imbalance, SOC, SOH, faults, diagnosis."""
    v = _fields(st, "voltages")
    v12, v24 = v.get("v12"), v.get("v24")
    imbalance = None
    if v12 is not None and v24 is not None:
        imbalance = Batteries.of(v12, v24).imbalance_v
    diagnosis = diagnose(v or None, st.status_flags)
    return {
        "unit": st.ref.sa,
        "bus": st.ref.bus,
        "name": st.name,
        "series": st.series,
        "model": st.model,
        "online": _online(st),
        "state": st.state(),
        "last_seen": st.last_seen,
        "parked_since": st.faults.parked_since,
        "v12": v12,
        "v24": v24,
        "imbalance_v": imbalance,
        "soc_12v": _fields(st, _SOC_SLOTS["soc_12v"]).get("soc"),
        "soc_24v": _fields(st, _SOC_SLOTS["soc_24v"]).get("soc"),
        "soh_12v": _fields(st, _SOH_SLOTS["soh_12v"]).get("soh"),
        "soh_24v": _fields(st, _SOH_SLOTS["soh_24v"]).get("soh"),
        "active_faults": sorted(st.faults.open),
        "faults": [
            {"fault": ep.fault, "state": ep.state, "occurrence_count": ep.occurrence_count}
            for _, ep in sorted(st.faults.open.items())
        ],
        "diagnosis": {"condition": diagnosis["condition"], "text": diagnosis["text"]},
    }


async def _fleet(rt: Runtime) -> dict[str, dict[str, Any]]:
    """Configured and stored vehicles with their stored units, cached briefly."""

    async def load() -> dict[str, dict[str, Any]]:
        def run(conn: Any) -> dict[str, dict[str, Any]]:
            vehicles: dict[str, dict[str, Any]] = {
                v["id"]: {**v, "stored_units": []} for v in queries.list_vehicles(conn)
            }
            for u in queries.list_units(conn):
                if u["vehicle_id"] in vehicles:
                    vehicles[u["vehicle_id"]]["stored_units"].append(u)
            return vehicles

        stored: dict[str, dict[str, Any]] = await rt.db(run)
        for v in rt.settings.vehicles:
            stored.setdefault(
                v.id, {"id": v.id, "name": v.display_name, "depot": v.depot, "stored_units": []}
            )
        return stored

    try:
        fleet: dict[str, dict[str, Any]] = await rt.cached("fleet", rt.api.fleet_cache_s, load)
    except (OperationalError, InterfaceError, PoolTimeout):
        # The database away: the fleet as last read, else as configured; the live view
        # itself is in memory, so /vehicles and /live go on answering.
        hit = rt._cache.get("fleet")
        if hit is not None:
            last: dict[str, dict[str, Any]] = hit[1]
            return last
        return {
            v.id: {"id": v.id, "name": v.display_name, "depot": v.depot, "stored_units": []}
            for v in rt.settings.vehicles
        }
    return fleet


async def _vehicle(rt: Runtime, vehicle_id: str) -> dict[str, Any]:
    """A vehicle in the scope (resolved by `VehicleId`) as the fleet listing has it."""
    fleet = await _fleet(rt)
    v = fleet.get(vehicle_id)
    if v is None and rt.ingest.live.of_vehicle(vehicle_id):
        v = {"id": vehicle_id, "name": vehicle_id, "depot": None, "stored_units": []}
    if v is None:
        raise unknown_vehicle(vehicle_id)
    return v


VEHICLE_STATES = ("ok", "attention", "offline", "parked", "not_reporting")
# How long past its time a fleet listing is still served while a fresh one renders.
LISTING_MAX_STALE_S = 2.0
# The most vehicles one page of `GET /vehicles` holds.
VEHICLES_PAGE_MAX = 1000


@router.get(
    "/vehicles",
    summary="The fleet with each unit's live summary; filtered by depot, state and search, paged",
    responses=errors(422),
    response_model=VehicleList,
)
async def list_vehicles(
    *,
    depot: str | None = Query(
        default=None, max_length=200, description="only this depot (exact, case-sensitive)"
    ),
    state: str | None = Query(
        default=None,
        max_length=200,
        description="only these states, comma-separated: " + ", ".join(VEHICLE_STATES),
        # Declared only: the route checks it and names the unknown states in its 422.
        json_schema_extra={
            "pattern": "^({0})(,({0}))*$".format("|".join(VEHICLE_STATES)),
        },
    ),
    search: str | None = Query(
        default=None,
        max_length=200,
        description="only vehicles whose id, name or depot contains this text (any case)",
    ),
    offset: int = Query(default=0, ge=0, description="vehicles skipped (ordered by id)"),
    limit: int | None = Query(
        default=None, ge=1, le=VEHICLES_PAGE_MAX, description="at most this many (default all)"
    ),
    rt: Rt,
    who: Viewer,
) -> Response:
    only = scope_filter(who)
    states = _states(state)
    # One rendering per scope: keys of one depot share theirs.
    name = "vehicles" if only is None else "vehicles:" + "\x1f".join(only)

    async def listing() -> dict[str, Any]:
        return await _fleet_listing(rt, None if only is None else set(only))

    # Rendered once per `live_cache_s` for every client: the units report every 3 s and
    # live changes reach the dashboard over the websocket, so a listing half a second old
    # is current, and 50 clients polling cost one render instead of fifty. Nobody waits for
    # a render but the first request: the others get the last listing while it is redone,
    # if it is at most LISTING_MAX_STALE_S past its time (else, after a quiet spell, the
    # request waits for a fresh one: a page loading would show minutes-old values that the
    # websocket then corrects, moving every tile).
    ttl = rt.api.live_cache_s
    rows: dict[str, Any] = await rt.cached(
        name + ":rows", ttl, listing, stale_while_loading=True, max_stale_s=LISTING_MAX_STALE_S
    )
    if not (depot or states or search or offset or limit):

        async def render() -> bytes:
            every = rows["vehicles"]
            return dumps({**rows, "total": len(every), "offset": 0, "limit": None})

        body: bytes = await rt.cached(
            name, ttl, render, stale_while_loading=True, max_stale_s=LISTING_MAX_STALE_S
        )
        return Response(body, media_type="application/json")
    return Response(
        dumps(_filtered(rows, depot, states, search, offset, limit)),
        media_type="application/json",
    )


def _states(value: str | None) -> set[str]:
    wanted = {s.strip() for s in (value or "").split(",") if s.strip()}
    unknown = sorted(wanted - set(VEHICLE_STATES))
    if unknown:
        raise ApiError(
            422,
            f"unknown state(s) {', '.join(unknown)}; known: {', '.join(VEHICLE_STATES)}",
            "invalid_state",
        )
    return wanted


def _filtered(
    rows: dict[str, Any],
    depot: str | None,
    states: set[str],
    search: str | None,
    offset: int,
    limit: int | None,
) -> dict[str, Any]:
    """One page of the vehicles matching every filter given; `total` counts every match and
    `counts` the states of the vehicles matching depot and search (for a summary bar)."""
    needle = (search or "").strip().casefold()
    matched = []
    counts = dict.fromkeys(VEHICLE_STATES, 0)
    for v in rows["vehicles"]:
        if depot and v.get("depot") != depot:
            continue
        if needle and not any(
            needle in str(v.get(k) or "").casefold() for k in ("id", "name", "depot")
        ):
            continue
        counts[v["state"]] = counts.get(v["state"], 0) + 1
        if states and v["state"] not in states:
            continue
        matched.append(v)
    end = None if limit is None else offset + limit
    return {
        "vehicles": matched[offset:end],
        "ts": rows["ts"],
        "total": len(matched),
        "offset": offset,
        "limit": limit,
        "counts": counts,
    }


# Vehicles summarised between two returns to the event loop while the listing renders:
# 200 vehicles take 15-30 ms, which would hold up every request, frame and websocket.
LISTING_CHUNK = 20


async def _fleet_listing(rt: Runtime, only: set[str] | None = None) -> dict[str, Any]:
    """The listing of every vehicle, or of those in `only` (a key's scope)."""
    fleet = await _fleet(rt)
    live = rt.ingest.live
    out = []
    ids = set(fleet) | live.vehicle_ids()
    if only is not None:
        ids &= only
    now = time.time()
    after = rt.settings.monitor.not_reporting_after_s
    for i, vid in enumerate(sorted(ids)):
        if i and not i % LISTING_CHUNK:
            await asyncio.sleep(0)
        v = fleet.get(vid, {"id": vid, "name": vid, "depot": None})
        units = sorted(live.of_vehicle(vid), key=lambda u: (u.ref.bus, u.ref.sa))
        out.append(
            {
                "id": vid,
                "name": v.get("name"),
                "depot": v.get("depot"),
                "online": any(_online(u) for u in units),
                **vehicle_status(units, now, after).to_dict(),
                "units": [unit_summary(u) for u in units],
            }
        )
    return {"vehicles": out, "ts": time.time()}


@router.get(
    "/vehicles/{vehicle_id}/live",
    summary="Every latest value per unit, status flags, active faults and the diagnosis",
    responses=errors(404),
    response_model=VehicleLive,
)
async def vehicle_live(
    rt: Rt,
    who: Viewer,
    vehicle_id: VehicleId,
) -> JsonResponse:
    v = await _vehicle(rt, vehicle_id)
    units = []
    for st in sorted(rt.ingest.live.of_vehicle(vehicle_id), key=lambda u: (u.ref.bus, u.ref.sa)):
        snap = st.snapshot()
        snap["unit"] = st.ref.sa
        snap["status_flags"] = st.status_flags
        snap["summary"] = unit_summary(st)
        snap["diagnosis"] = diagnose(_fields(st, "voltages") or None, st.status_flags)
        units.append(snap)
    status = vehicle_status(
        rt.ingest.live.of_vehicle(vehicle_id),
        time.time(),
        rt.settings.monitor.not_reporting_after_s,
    )
    return JsonResponse(
        {
            "id": vehicle_id,
            "name": v.get("name"),
            "depot": v.get("depot"),
            **status.to_dict(),
            "units": units,
        }
    )


def _stored_unit(v: dict[str, Any], unit: int | None) -> dict[str, Any]:
    units = v["stored_units"]
    if not units:
        raise ApiError(404, f"{v['id']} has no stored data yet", "no_data")
    if unit is None:
        return dict(units[0])
    for u in units:
        if u["sa"] == unit:
            return dict(u)
    raise ApiError(404, f"{v['id']} has no unit at SA {unit}", "unknown_unit")


# Points per field of one history answer, and status changes of one status answer; a range
# holding more is refused (422), not cut.
HISTORY_LIMIT = 100_000
STATUS_LIMIT = 10_000
# Fault episodes listed in one answer (newest first); `counts` and `total` cover them all.
FAULTS_LIMIT = 5000


@router.get(
    "/vehicles/{vehicle_id}/history",
    summary="Time series of one unit: JSON, or CSV with `Accept: text/csv` or `?format=csv`",
    responses={
        **errors(404, 422),
        200: {"content": {"text/csv": {"schema": {"type": "string"}}}},
    },
    response_model=History,
)
async def vehicle_history(
    *,
    request: Request,
    from_: str | None = Query(default=None, alias="from", description="Epoch s or ISO 8601"),
    to: str | None = Query(default=None, description="Epoch s or ISO 8601 (default now)"),
    bucket: str = Query(default="auto", description="raw, 1m, 15m, 1h, 1d or auto"),
    fields: str = Query(default="v12,v24", description="Comma-separated metrics"),
    unit: int | None = Query(default=None, ge=0, le=253),
    format: str | None = Query(default=None, pattern="^(json|csv)$"),
    rt: Rt,
    who: Viewer,
    vehicle_id: VehicleId,
) -> Response:
    v = await _vehicle(rt, vehicle_id)
    start, end = time_window(from_, to, 3600.0)
    names = [f.strip() for f in fields.split(",") if f.strip()]
    known = set(queries.metrics())
    unknown = [n for n in names if n not in known]
    if not names or unknown:
        raise ApiError(
            422,
            f"unknown field(s) {', '.join(unknown) or '(none given)'}; known: "
            + ", ".join(queries.metrics()),
            "invalid_fields",
        )
    if bucket == "auto":
        bucket = queries.pick_resolution(start, end)
    if bucket not in queries.RESOLUTIONS:
        raise ApiError(
            422, f"bucket is one of auto, {', '.join(queries.RESOLUTIONS)}", "invalid_bucket"
        )
    width = queries.RESOLUTIONS[bucket]
    if width is not None:
        # Refused from the count before anything is read: a year of 1 min buckets would be
        # read whole (seconds, and memory for every point) only to be refused afterwards.
        buckets = queries.bucket_count(start, end, width)
        if buckets > HISTORY_LIMIT:
            raise _too_many_points(names, bucket, HISTORY_LIMIT, span=(start, end))
    u = _stored_unit(v, unit)
    want_csv = format == "csv" or (
        format is None and "text/csv" in request.headers.get("accept", "")
    )

    # The body is made in the worker thread too: thousands of points as dicts, then JSON or
    # CSV, would otherwise hold the event loop for milliseconds.
    def run(conn: Any) -> bytes:
        limit = HISTORY_LIMIT
        # One point more than the limit: more than `limit` is refused, never cut silently.
        series = queries.series_many(
            conn, u["id"], names, start, end, bucket, limit=limit + 1, cache=rt.history
        )
        owners = queries.unit_owners(conn, u["id"], start, end)
        over = [n for n, points in series.items() if len(points) > limit]
        if over:
            raise _too_many_points(over, bucket, limit)
        if want_csv:
            return _history_csv(series, bucket).encode()
        return dumps(
            {
                "vehicle_id": vehicle_id,
                "unit": u["sa"],
                "bus": u["bus"],
                "from": start,
                "to": end,
                "bucket": bucket,
                "name": u.get("name"),
                "owners": owners,
                "series": series,
            }
        )

    body: bytes = await rt.db(run)
    return Response(body, media_type="text/csv" if want_csv else "application/json")


def _too_many_points(
    over: list[str], bucket: str, limit: int, *, span: tuple[float, float] | None = None
) -> ApiError:
    """The 422 of a history over the limit. With `span` (refused from the bucket count), the
    wider buckets suggested are those within the limit over that range."""
    width = queries.RESOLUTIONS[bucket] or 0
    wider = [r for r, w in queries.RESOLUTIONS.items() if (w or 0) > width]
    extra: dict[str, Any] = {"limit": limit, "fields": over}
    if span is not None:
        extra["buckets"] = queries.bucket_count(span[0], span[1], width)
        wider = [
            r
            for r in wider
            if queries.bucket_count(span[0], span[1], queries.RESOLUTIONS[r] or 1) <= limit
        ]
    what = "raw points" if bucket == "raw" else f"{bucket} buckets"
    return ApiError(
        422,
        f"the range holds more than {limit} {what} of {', '.join(over)} (at most {limit} per "
        "field are returned, and never a cut series); ask for a shorter range"
        + (f" or a wider bucket ({', '.join(wider)})" if wider else ""),
        "too_many_points",
        extra=extra,
    )


def _history_csv(series: Mapping[str, Sequence[Mapping[str, object]]], bucket: str) -> str:
    buf = io.StringIO()
    w = csv.writer(buf)
    if bucket == "raw":
        w.writerow(["ts", "field", "value"])
        for n, points in series.items():
            w.writerows([p["ts"], n, p["value"]] for p in points)
    else:
        w.writerow(["ts", "field", "count", "min", "max", "avg"])
        for n, points in series.items():
            w.writerows([p["ts"], n, p["count"], p["min"], p["max"], p["avg"]] for p in points)
    return buf.getvalue()


@router.get(
    "/vehicles/{vehicle_id}/status",
    summary="Status-flag changes of one unit (the flags after each change and which changed)",
    responses=errors(404, 422),
    response_model=StatusHistory,
)
async def vehicle_status_history(
    *,
    from_: str | None = Query(default=None, alias="from", description="Epoch s or ISO 8601"),
    to: str | None = Query(default=None, description="Epoch s or ISO 8601 (default now)"),
    unit: int | None = Query(default=None, ge=0, le=253),
    rt: Rt,
    who: Viewer,
    vehicle_id: VehicleId,
) -> JsonResponse:
    v = await _vehicle(rt, vehicle_id)
    start, end = time_window(from_, to, 3600.0)
    u = _stored_unit(v, unit)

    def run(conn: Any) -> list[queries.StatusRow]:
        return queries.status_history(conn, u["id"], start, end, limit=STATUS_LIMIT + 1)

    changes = await rt.db(run)
    if len(changes) > STATUS_LIMIT:
        raise ApiError(
            422,
            f"the range holds more than {STATUS_LIMIT} status changes (at most {STATUS_LIMIT} "
            "are returned, and never a cut list); ask for a shorter range",
            "too_many_points",
            extra={"limit": STATUS_LIMIT},
        )
    return JsonResponse(
        {"vehicle_id": vehicle_id, "unit": u["sa"], "from": start, "to": end, "changes": changes}
    )


def _counts(episodes: Sequence[Mapping[str, Any]]) -> dict[str, dict[str, Any]]:
    counts: dict[str, dict[str, Any]] = {}
    for e in episodes:
        c = counts.setdefault(e["fault"], {"episodes": 0, "occurrence_count": None, "active": 0})
        c["episodes"] += 1
        if e["state"] != "closed":
            c["active"] += 1
        oc = e.get("occurrence_count")
        if oc is not None and (c["occurrence_count"] is None or oc > c["occurrence_count"]):
            c["occurrence_count"] = oc
    return counts


async def _faults(
    rt: Runtime,
    vehicle_ids: list[str] | None,
    vehicle_id: str | None,
    active: bool,
    from_: str | None,
    to: str | None,
    code: str | None,
    as_csv: bool = False,
) -> Response:
    start, end = time_filter(from_, to)
    filters: dict[str, Any] = {"vehicle_id": vehicle_id, "start": start, "end": end, "fault": code}
    if as_csv:
        return faults_csv(rt, vehicle_ids, open_only=active, **filters)

    def run(conn: Any) -> list[queries.UnitEpisodeRow]:
        return queries.fault_episodes(conn, vehicle_ids=vehicle_ids, open_only=active, **filters)

    episodes = await rt.db(run)
    return JsonResponse(
        {
            "episodes": episodes[:FAULTS_LIMIT],
            "counts": _counts(episodes),
            "total": len(episodes),
            "truncated": len(episodes) > FAULTS_LIMIT,
        }
    )


_CSV_DOC = "json (default), or csv: every episode streamed, as `Accept: text/csv` asks"


@router.get(
    "/vehicles/{vehicle_id}/faults",
    summary="Fault episodes and occurrence counts of one vehicle: JSON, or CSV",
    responses={**errors(404, 422), 200: {"content": csv_export.CSV_CONTENT}},
    response_model=FaultList,
)
async def vehicle_faults(
    *,
    request: Request,
    active: bool = False,
    from_: str | None = Query(default=None, alias="from", description="Epoch s or ISO 8601"),
    to: str | None = Query(default=None, description="Epoch s or ISO 8601"),
    code: str | None = Query(default=None, max_length=64, description="e.g. OVF, IMB"),
    format: str | None = Query(default=None, pattern="^(json|csv)$", description=_CSV_DOC),
    rt: Rt,
    who: Viewer,
    vehicle_id: VehicleId,
) -> Response:
    await _vehicle(rt, vehicle_id)
    as_csv = csv_export.wants_csv(request, format)
    return await _faults(rt, scope_filter(who), vehicle_id, active, from_, to, code, as_csv)


@router.get(
    "/faults",
    summary="Fault episodes and occurrence counts, fleet-wide or of a depot: JSON, or CSV",
    responses={**errors(422), 200: {"content": csv_export.CSV_CONTENT}},
    response_model=FaultList,
)
async def fleet_faults(
    *,
    request: Request,
    active: bool = False,
    from_: str | None = Query(default=None, alias="from", description="Epoch s or ISO 8601"),
    to: str | None = Query(default=None, description="Epoch s or ISO 8601"),
    code: str | None = Query(default=None, max_length=64),
    vehicle: str | None = Query(default=None, max_length=64),
    depot: str | None = Query(default=None, max_length=200, description="the fleet file's depot"),
    format: str | None = Query(default=None, pattern="^(json|csv)$", description=_CSV_DOC),
    rt: Rt,
    who: Viewer,
) -> Response:
    as_csv = csv_export.wants_csv(request, format)
    vehicle_ids = vehicles_of(rt, who, depot)
    return await _faults(rt, vehicle_ids, vehicle, active, from_, to, code, as_csv)


FAULT_COLUMNS = (
    "id",
    "vehicle_id",
    "bus",
    "sa",
    "fault",
    "spn",
    "fmi",
    "source",
    "state",
    "started_at",
    "last_seen_at",
    "ended_at",
    "ended_by",
    "occurrence_count",
)


def faults_csv(rt: Runtime, vehicle_ids: list[str] | None, **filters: Any) -> StreamingResponse:
    """Fault episodes (`queries.fault_episodes` filters), with the unit's occurrence count, in
    id order."""

    def page(conn: Connection, after: int, limit: int) -> list[queries.UnitEpisodeRow]:
        return queries.fault_episodes(
            conn, vehicle_ids=vehicle_ids, after_id=after, limit=limit, **filters
        )

    return csv_export.stream(rt, "faults", FAULT_COLUMNS, page)
