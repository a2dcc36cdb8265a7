"""Frames uploaded by edge forwarders (`eqgw forward`): `POST /ingest/frames`, ingest keys only.

`forwarding`, the last part of the gateway's lifespan (eqgw.main), restores the forwarded
buses' units into the live view, so `/vehicles`, `/live` and websocket snapshots show
forwarded vehicles from the start, offline until they upload again.
"""

from __future__ import annotations

import gzip
import logging
import zlib
from collections.abc import AsyncIterator, Callable, Coroutine, Iterator
from contextlib import asynccontextmanager
from typing import Annotated, Any, Literal

from fastapi import APIRouter, Depends, FastAPI, Request, Response
from fastapi.routing import APIRoute
from prometheus_client.core import CounterMetricFamily, Metric
from prometheus_client.registry import Collector
from pydantic import BaseModel, ConfigDict, Field

from eqgw.forward.central import ForwardIngest, ForwardRefused, Upload
from eqgw.forward.protocol import MAX_FRAMES_PER_UPLOAD
from eqgw.security.auth import require
from eqgw.security.keys import INGEST, Principal
from eqgw.web.errors import ApiError
from eqgw.web.responses import JsonResponse
from eqgw.web.runtime import Runtime
from eqgw.web.schemas import RequestBody, errors

log = logging.getLogger(__name__)

# A gzip body may not inflate beyond this (a compressed upload of 20,000 frames is ~1 MB).
MAX_BODY_BYTES = 16 * 1024 * 1024


class _GzipRequest(Request):
    """A request whose `Content-Encoding: gzip` body is inflated before FastAPI parses it."""

    async def body(self) -> bytes:
        if not hasattr(self, "_body"):
            raw = await super().body()
            if "gzip" in self.headers.get("content-encoding", "").lower():
                try:
                    d = zlib.decompressobj(16 + zlib.MAX_WBITS)
                    raw = d.decompress(raw, MAX_BODY_BYTES + 1)
                except (zlib.error, gzip.BadGzipFile) as exc:
                    raise ApiError(400, f"body is not valid gzip: {exc}") from exc
                if len(raw) > MAX_BODY_BYTES:
                    raise ApiError(413, f"body inflates beyond {MAX_BODY_BYTES} bytes")
            self._body = raw
        return self._body


class _GzipRoute(APIRoute):
    def get_route_handler(self) -> Callable[[Request], Coroutine[Any, Any, Response]]:
        handler = super().get_route_handler()

        async def gzip_handler(request: Request) -> Response:
            return await handler(_GzipRequest(request.scope, request.receive))

        return gzip_handler


def _make_forward_ingest(app: FastAPI) -> ForwardIngest:
    rt: Runtime = app.state.rt
    fwd = ForwardIngest(rt.settings, rt.engine, rt.ingest.hub, rt.ingest.live)
    app.state.forward_ingest = fwd
    return fwd


@asynccontextmanager
async def forwarding(app: FastAPI) -> AsyncIterator[None]:
    """The refused frames' metric, and the forwarded units restored into the live view."""
    metrics = getattr(app.state, "metrics", None)
    collector = RefusedFramesCollector(app)
    if metrics is not None:
        metrics.registry.register(collector)
    if getattr(app.state, "rt", None) is not None:
        fwd = _make_forward_ingest(app)
        try:
            n = await fwd.restore_live()
        except Exception as exc:  # each stream's first upload restores its units anyway
            log.warning("forwarded units not restored into the live view: %s", exc)
        else:
            if n:
                log.info("restored the live state of %d forwarded units", n)
    try:
        yield
    finally:
        app.state.forward_ingest = None
        if metrics is not None:
            metrics.registry.unregister(collector)


router = APIRouter(tags=["ingest"], responses=errors(401, 403), route_class=_GzipRoute)
ingest_key = require(INGEST, audited=True)
IngestKey = Annotated[Principal, Depends(ingest_key)]

Sa = Annotated[int, Field(ge=0, le=253)]
Frame = tuple[float, Annotated[int, Field(ge=0, le=0x1FFFFFFF)], str, Annotated[int, Field(ge=0)]]


class FrameUpload(RequestBody):
    """A batch of a forwarder's buffered frames, with consecutive sequence numbers."""

    model_config = ConfigDict(extra="forbid")
    nul_unchecked = frozenset({"frames"})  # hex data: anything but hex digits is refused

    stream: str = Field(
        min_length=1,
        max_length=64,
        pattern=r"^[A-Za-z0-9._:-]+$",
        description="The forwarder buffer's id (a uuid made when the buffer was created)",
    )
    vehicle: str = Field(min_length=1, max_length=64, description="A configured vehicle id")
    bus: str | None = Field(
        default=None,
        min_length=1,
        max_length=200,
        description="Bus name the units are filed under: the vehicle id or `<vehicle>/...`",
    )
    equalizer_sas: list[Sa] = Field(default=[30], min_length=1, max_length=16)
    first_seq: int = Field(ge=1, le=2**62, description="Sequence number of frames[0]")
    frames: list[Frame] = Field(
        max_length=MAX_FRAMES_PER_UPLOAD,
        description="[timestamp s, 29/11-bit id, data as hex, flags: 1 extended 2 remote 4 error]",
    )
    dropped: int = Field(default=0, ge=0, le=2**62, description="Frames the buffer dropped")


class UploadAck(BaseModel):
    """What was stored: `acked_seq` is committed; the forwarder may forget up to it."""

    stream: str
    acked_seq: int
    stored: int
    duplicates: int
    refused: int = Field(
        default=0,
        description="Frames not stored for their time, yet acknowledged (sending them again "
        "changes nothing): more than `forward.max_future_s` ahead of the gateway's clock, or "
        "older than the raw retention",
    )
    refused_reasons: dict[Literal["future", "too_old"], int] = Field(
        default={}, description="The refused frames by reason (reasons with none left out)"
    )


class RefusedFramesCollector(Collector):
    """Frames refused for their time, per forwarder stream (read when Prometheus scrapes)."""

    def __init__(self, app: FastAPI) -> None:
        self.app = app

    def collect(self) -> Iterator[Metric]:
        refused = CounterMetricFamily(
            "eqgw_forward_frames_refused",
            "Forwarded frames refused for their time (acknowledged, not stored), per stream: "
            "future (beyond forward.max_future_s) or too_old (beyond the raw retention)",
            labels=["bus", "reason", "stream", "vehicle"],
        )
        fwd: ForwardIngest | None = getattr(self.app.state, "forward_ingest", None)
        if fwd is not None:
            for (stream, vehicle, bus), counts in list(fwd.refused.items()):
                for reason, n in counts.items():
                    refused.add_metric([bus, reason, stream, vehicle], n)
        yield refused


def forward_ingest(request: Request) -> ForwardIngest:
    """The process's ForwardIngest, made on first use from the running gateway."""
    fwd: ForwardIngest | None = getattr(request.app.state, "forward_ingest", None)
    if fwd is None:
        fwd = _make_forward_ingest(request.app)
    return fwd


@router.post(
    "/ingest/frames",
    response_model=UploadAck,
    summary="Store a batch of frames from an edge forwarder (ingest keys only)",
    responses=errors(400, 404, 409, 413, 422, 503),
)
async def post_frames(
    body: FrameUpload,
    request: Request,
    principal: IngestKey,
) -> JsonResponse:
    """Frames of one vehicle bus, decoded and stored as a replay of them would be; answered
    once committed. A batch sent again is stored once. `Content-Encoding: gzip` is accepted."""
    if not principal.sees(body.vehicle):
        detail = f"this ingest key is not bound to vehicle {body.vehicle!r}"
        rt: Runtime = request.app.state.rt
        await rt.audit(
            principal,
            "ingest.frames",
            outcome="refused",
            status=403,
            detail=detail,
            vehicle_id=body.vehicle,
            target=f"stream {body.stream}",
        )
        raise ApiError(403, detail, "out_of_scope")
    fwd = forward_ingest(request)
    sas = tuple(dict.fromkeys(body.equalizer_sas))
    upload = Upload(
        stream=body.stream,
        vehicle=body.vehicle,
        bus=body.bus or body.vehicle,
        equalizer_sas=sas,
        first_seq=body.first_seq,
        frames=body.frames,
        dropped=body.dropped,
    )
    if upload.last_seq > 2**62:
        raise ApiError(422, "sequence numbers beyond 2**62")
    try:
        ack = await fwd.take(upload, principal.lineage or principal.key_id)
    except ForwardRefused as exc:
        raise ApiError(exc.status, exc.detail) from exc
    return JsonResponse(ack)
