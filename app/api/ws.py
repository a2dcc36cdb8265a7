"""The websocket: live values, status and fault changes, command states, with a snapshot first.

Protocol (JSON text frames). Connect to `/api/v1/ws?key=<key>&vehicles=A,B` (or an
`Authorization: Bearer` header; `vehicles` omitted or `*` = all). The server sends
`{"type": "snapshot", "vehicle_id", "units": [...]}` per subscribed vehicle, then events
`{"type": <kind>, "vehicle_id", "bus", "unit", "ts", "data"}` with kind `live`, `status_change`,
`fault_open`, `fault_update`, `fault_stale`, `fault_close`, `unit_online`, `command`, or
`alert_raised` / `alert_acknowledged` / `alert_cleared` (`data`: the alert). The client
may send `{"type": "subscribe", "vehicles": [...] | "*"}` or `{"type": "unsubscribe", ...}`:
subscribe adds the vehicles and sends their snapshots (subscribed to all, it stays all and
takes back any earlier unsubscribe of them; `*` restores all); unsubscribe removes them
(subscribed to all, all but those, vehicles seen later included). A binary frame or a bad
message gets an error and the connection stays open.
A client that falls `ws_queue` events behind gets `{"type": "error", "reason": ...}` and is
closed with code 1008: it never slows the ingest or other clients. The key is checked again
every `KEY_RECHECK_S` through the authenticator's cache (no cost per event): once it is
revoked (within `KEY_RECHECK_S` in the revoking process, which drops the cache; within the
cache's TTL plus that when revoked by another process) the client gets an error and close
code 4401.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from typing import Any

import orjson
from fastapi import APIRouter, WebSocket, WebSocketDisconnect

from app.api.deps import Runtime, authenticate
from app.api.responses import dumps
from app.ingest import events
from app.ingest.events import Event
from app.ingest.hub import SubscriberLagged, Subscription

router = APIRouter()
log = logging.getLogger(__name__)

WS_KINDS = events.UNIT_KINDS | events.ALERT_KINDS
CLOSE_UNAUTHORIZED = 4401
CLOSE_SLOW = 1008
# How often an open connection's key is checked again (a cache hit: no I/O, but the cache
# expires every `key_cache_s`, and a revocation in this process drops it at once).
KEY_RECHECK_S = 1.0
REVOKED_REASON = "the API key was revoked or is no longer valid"


class _Selection:
    """The vehicles a client wants: `vehicles`, or (None) every vehicle but `excluded`."""

    def __init__(self, vehicles: set[str] | None) -> None:
        self.vehicles = vehicles
        self.excluded: set[str] = set()

    def wants(self, event: Event) -> bool:
        vid = event.unit.vehicle_id
        if self.vehicles is None:
            return vid not in self.excluded
        return vid in self.vehicles

    def subscribe(self, vehicles: set[str] | None) -> set[str] | None:
        """Add `vehicles` (None = all); returns whose snapshots to send (None = all)."""
        if vehicles is None:
            self.vehicles, self.excluded = None, set()
            return None
        if self.vehicles is None:
            self.excluded -= vehicles
            return vehicles
        added = vehicles - self.vehicles
        self.vehicles |= vehicles
        return added

    def unsubscribe(self, vehicles: set[str] | None) -> None:
        """Remove `vehicles` (None = all); from all, the rest (and vehicles seen later) stay."""
        if vehicles is None:
            self.vehicles, self.excluded = set(), set()
        elif self.vehicles is None:
            self.excluded |= vehicles
        else:
            self.vehicles -= vehicles


def _parse_vehicles(value: Any) -> set[str] | None:
    if value is None or value == "*" or value == ["*"]:
        return None
    if isinstance(value, str):
        return {v for v in value.split(",") if v}
    if isinstance(value, list):
        return {str(v) for v in value}
    raise ValueError("vehicles is a list of ids or '*'")


def _event_message(event: Event) -> bytes:
    return dumps(
        {
            "type": event.kind,
            "vehicle_id": event.unit.vehicle_id,
            "bus": event.unit.bus,
            "unit": event.unit.sa,
            "ts": event.ts,
            "data": event.data,
        }
    )


def _snapshots(rt: Runtime, vehicles: set[str] | None) -> list[bytes]:
    live = rt.ingest.live
    ids = (
        sorted(
            {u.ref.vehicle_id for u in live.units.values()} | {v.id for v in rt.settings.vehicles}
        )
        if vehicles is None
        else sorted(vehicles)
    )
    return [
        dumps({"type": "snapshot", "vehicle_id": vid, "units": live.snapshot(vid)}) for vid in ids
    ]


@router.websocket("/api/v1/ws")
async def websocket(ws: WebSocket) -> None:
    rt: Runtime = ws.app.state.rt
    token = ws.query_params.get("key")
    auth = ws.headers.get("authorization", "")
    if not token and auth.lower().startswith("bearer "):
        token = auth[7:].strip()
    principal = await authenticate(rt, token)
    await ws.accept()
    if principal is None or not principal.allows("viewer"):  # an ingest key reads nothing
        await ws.send_text('{"type":"error","reason":"a valid API key is required"}')
        await ws.close(CLOSE_UNAUTHORIZED, "unauthorized")
        return
    try:
        selection = _Selection(_parse_vehicles(ws.query_params.get("vehicles")))
    except ValueError as exc:
        await ws.close(1003, str(exc))
        return
    maxsize = rt.api.ws_queue
    subs: list[Subscription] = [
        rt.ingest.hub.subscribe(WS_KINDS, maxsize=maxsize, predicate=selection.wants),
        rt.commands.hub.subscribe(None, maxsize=maxsize, predicate=selection.wants),
    ]
    control: asyncio.Queue[bytes] = asyncio.Queue()
    try:
        # Snapshots go out before any event, so a client never starts blank.
        for msg in _snapshots(rt, selection.vehicles):
            await ws.send_text(msg.decode())
    except (WebSocketDisconnect, RuntimeError):
        for sub in subs:
            sub.close()
        return
    reader = asyncio.create_task(_read_client(ws, rt, selection, control))
    watcher = asyncio.create_task(_watch_key(rt, token))
    try:
        await _pump(ws, rt, subs, control, reader, watcher)
    finally:
        for task in (reader, watcher):
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await task
        for sub in subs:
            sub.close()


async def _read_client(
    ws: WebSocket, rt: Runtime, selection: _Selection, control: asyncio.Queue[bytes]
) -> None:
    """Handle subscribe/unsubscribe messages; ends when the client goes away."""
    while True:
        try:
            message = await ws.receive()
        except (WebSocketDisconnect, RuntimeError):
            return
        if message["type"] == "websocket.disconnect":
            return
        raw = message.get("text")
        if raw is None:
            reason = "binary frames are not understood: send JSON text frames"
            control.put_nowait(dumps({"type": "error", "reason": reason}))
            continue
        try:
            msg = orjson.loads(raw)
            kind = msg.get("type")
            vehicles = _parse_vehicles(msg.get("vehicles", "*"))
        except (orjson.JSONDecodeError, AttributeError, ValueError) as exc:
            control.put_nowait(dumps({"type": "error", "reason": f"bad message: {exc}"}))
            continue
        if kind == "subscribe":
            for snap in _snapshots(rt, selection.subscribe(vehicles)):
                control.put_nowait(snap)
        elif kind == "unsubscribe":
            selection.unsubscribe(vehicles)
        else:
            control.put_nowait(dumps({"type": "error", "reason": f"unknown type {kind!r}"}))


async def _watch_key(rt: Runtime, token: str | None) -> str:
    """Check the connection's key every `KEY_RECHECK_S`; returns why it is no longer valid.

    A check is a hit in the authenticator's cache (no I/O) unless the cache expired or was
    dropped by a revocation in this process, so it costs nothing per event.
    """
    while True:
        await asyncio.sleep(KEY_RECHECK_S)
        try:
            principal = await authenticate(rt, token)
        except Exception:  # the database unreachable is no revocation: check again later
            log.warning("websocket key re-check failed", exc_info=True)
            continue
        if principal is None:
            return REVOKED_REASON
        if not principal.allows("viewer"):
            return f"the {principal.role} role cannot read the fleet"


async def _pump(
    ws: WebSocket,
    rt: Runtime,
    subs: list[Subscription],
    control: asyncio.Queue[bytes],
    reader: asyncio.Task[None],
    watcher: asyncio.Task[str],
) -> None:
    """Send snapshots and events in order until the client leaves or falls behind, or its
    key is revoked."""
    timeout = rt.api.ws_send_timeout_s
    getters: dict[asyncio.Future[Any], Any] = {asyncio.ensure_future(control.get()): control}
    for sub in subs:
        getters[asyncio.ensure_future(sub.get())] = sub
    getters[reader] = None
    getters[watcher] = None
    try:
        while True:
            done, _ = await asyncio.wait(getters, return_when=asyncio.FIRST_COMPLETED)
            if reader in done:
                return  # the client left
            if watcher in done:
                reason = watcher.result()
                with contextlib.suppress(Exception):
                    async with asyncio.timeout(timeout):
                        await ws.send_text(dumps({"type": "error", "reason": reason}).decode())
                        await ws.close(CLOSE_UNAUTHORIZED, reason)
                return
            for fut in done:
                source = getters.pop(fut)
                try:
                    item = fut.result()
                except SubscriberLagged:
                    reason = f"slow consumer: fell {rt.api.ws_queue} events behind"
                    with contextlib.suppress(Exception):
                        async with asyncio.timeout(timeout):
                            await ws.send_text(dumps({"type": "error", "reason": reason}).decode())
                            await ws.close(CLOSE_SLOW, reason)
                    return
                except StopAsyncIteration:
                    return  # the hub closed: the gateway is stopping
                data = item if isinstance(item, bytes) else _event_message(item)
                try:
                    async with asyncio.timeout(timeout):
                        await ws.send_text(data.decode())
                except (TimeoutError, WebSocketDisconnect, RuntimeError):
                    return
                # Drain what is already queued without a round through asyncio.wait.
                if isinstance(source, Subscription):
                    while (more := _next_nowait(source)) is not None:
                        async with asyncio.timeout(timeout):
                            await ws.send_text(_event_message(more).decode())
                    getters[asyncio.ensure_future(source.get())] = source
                else:
                    getters[asyncio.ensure_future(control.get())] = control
    except (TimeoutError, WebSocketDisconnect, RuntimeError):
        return
    except SubscriberLagged:
        reason = f"slow consumer: fell {rt.api.ws_queue} events behind"
        with contextlib.suppress(Exception):
            async with asyncio.timeout(timeout):
                await ws.send_text(dumps({"type": "error", "reason": reason}).decode())
                await ws.close(CLOSE_SLOW, reason)
    finally:
        for fut in getters:
            if fut is not reader and fut is not watcher:
                fut.cancel()


def _next_nowait(sub: Subscription) -> Event | None:
    return sub.get_nowait()
