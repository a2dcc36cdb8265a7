"""`GET /vehicles/{id}/raw`: a vehicle's archived CAN frames as a log file (candump, ASC,
BLF or MF4), streamed.

The archive is read a page at a time (eqgw.store.archive.read_page, a quarter of an hour of
history), each page in its own short transaction in a worker thread, turned into the file's
bytes there (eqgw.bus.export) and sent before the next page is read: a month of a vehicle is
answered holding one page (bench/raw_export.py gives the figures). BLF and MF4 are finished at
their end (their headers say what follows): they are made in a temporary file first, then
sent from it. A failure after the first bytes were sent closes the connection without the
chunked body's end, so a cut export is never taken for a whole one (as the CSV exports).
"""

from __future__ import annotations

import asyncio
import re
from collections.abc import AsyncIterator
from typing import Annotated, Any, Literal

from fastapi import APIRouter, Query
from fastapi.responses import StreamingResponse
from sqlalchemy import Connection

from eqgw.bus.export import FORMATS, MEDIA_TYPES, ExportError, LogExport, mf4_available
from eqgw.fleet.endpoints import _vehicle
from eqgw.security.auth import VehicleId, Viewer
from eqgw.store import archive
from eqgw.web.errors import ApiError
from eqgw.web.runtime import Rt, Runtime
from eqgw.web.times import time_window

Format = Literal["candump", "asc", "blf", "mf4"]


class RawLogResponse(StreamingResponse):
    """A streamed log file (the class gives the OpenAPI document its first media type)."""

    media_type = "application/octet-stream"


def _errors(*codes: int) -> dict[int | str, dict[str, Any]]:
    schema = {"schema": {"$ref": "#/components/schemas/ErrorBody"}}
    return {c: {"description": "Error", "content": {"application/json": schema}} for c in codes}


_LOG_CONTENT = {
    # Binary first: a client generated from the document takes any of the four as bytes.
    "application/octet-stream": {"schema": {"type": "string", "format": "binary"}},
    "text/plain": {"schema": {"type": "string"}},
}

router = APIRouter(tags=["exports"], default_response_class=RawLogResponse)


def channels_of(units: list[dict[str, Any]]) -> dict[int, int]:
    """Unit id -> the log channel of its bus: the vehicle's buses in name order, 0, 1, ..."""
    buses = sorted({u["bus"] for u in units})
    return {u["id"]: buses.index(u["bus"]) for u in units}


@router.get(
    "/vehicles/{vehicle_id}/raw",
    summary="A vehicle's archived CAN frames as a log file: candump, ASC, BLF or MF4",
    responses={
        200: {
            "description": "The log file: candump and ASC are text (text/plain), BLF and MF4 "
            "binary (application/octet-stream)",
            "content": _LOG_CONTENT,
        },
        **_errors(401, 403, 404, 422),
    },
)
async def vehicle_raw(
    *,
    from_: Annotated[
        str | None,
        Query(alias="from", description="Epoch s or ISO 8601 (default `to` - 1 h)"),
    ] = None,
    to: Annotated[str | None, Query(description="Epoch s or ISO 8601 (default now)")] = None,
    format: Annotated[Format, Query(description="candump (-L), asc, blf or mf4")] = "candump",
    rt: Rt,
    who: Viewer,
    vehicle_id: VehicleId,
) -> StreamingResponse:
    """Every equalizer frame archived from the vehicle's buses with `from` <= time < `to`,
    in time order, written with python-can's writers. The vehicle's buses are log channels
    0, 1, ... in name order (candump `can0`, ASC and BLF channel 1, ...; the
    `X-Eqgw-Channels` header names them)."""
    v = await _vehicle(rt, vehicle_id)
    start, end = time_window(from_, to, 3600.0)
    if format == "mf4" and not mf4_available():
        raise ApiError(422, "MF4 needs asammdf on the gateway (eqgw[mf4])", "format_unavailable")
    units = v["stored_units"]
    channels = channels_of(units)
    buses = sorted({u["bus"] for u in units})
    try:
        export = LogExport(format)
    except ExportError as exc:
        raise ApiError(422, str(exc), "format_unavailable") from exc
    name = re.sub(r"[^A-Za-z0-9._-]", "_", vehicle_id)
    return RawLogResponse(
        _body(rt, export, channels, start, end),
        media_type=MEDIA_TYPES[format],
        headers={
            "Content-Disposition": (
                f'attachment; filename="{name}-{int(start)}-{int(end)}{FORMATS[format]}"'
            ),
            "X-Eqgw-Channels": ", ".join(f"{i}={b}" for i, b in enumerate(buses)),
        },
    )


async def _body(
    rt: Runtime, export: LogExport, channels: dict[int, int], start: float, end: float
) -> AsyncIterator[bytes]:
    """The file's bytes, page after page, then (BLF, MF4) the finished file."""
    unit_ids = sorted(channels)
    try:
        cursor: float | None = start
        while cursor is not None:

            def page(conn: Connection, after: float = cursor) -> tuple[bytes, float | None]:
                frames, following = archive.read_page(conn, unit_ids, after, end)
                return export.write([(channels[u], f) for u, f in frames]), following

            chunk, cursor = await rt.db_page(page)
            if chunk:
                yield chunk
        tail = await asyncio.to_thread(export.finish)
        if tail:
            yield tail
        while chunk := await asyncio.to_thread(export.read):
            yield chunk
    finally:
        export.close()  # removes a temporary file: quick, and sure to run on a cancel too
