"""The websocket: live values, status and fault changes, command states, with a snapshot first.

Protocol (JSON text frames). Connect to `/api/v1/ws?vehicles=A,B` (`vehicles` omitted or `*` =
all) with the dashboard's session cookie (same origin only), an `Authorization: Bearer` header,
or, with neither, `{"type": "auth", "key": "<key>"}` as the first message within 5 s
(`?key=<key>` is still accepted, but puts the key in URLs and logs). The server sends
`{"type": "snapshot", "vehicle_id", "vehicle": {"state", "last_heard", "parked_since"},
"units": [...]}` per subscribed vehicle, then events
`{"type": <kind>, "vehicle_id", "bus", "unit", "ts", "data"}` with kind `live`, `status_change`,
`fault_open`, `fault_update`, `fault_stale`, `fault_close`, `unit_online`, `unit_parked`,
`vehicle_state` (`data`: the vehicle's new state, last_heard, parked_since), `command`, or
`alert_raised` / `alert_acknowledged` / `alert_cleared` (`data`: the alert). The client
may send `{"type": "subscribe", "vehicles": [...] | "*"}` or `{"type": "unsubscribe", ...}`:
subscribe adds the vehicles and sends their snapshots (subscribed to all, it stays all and
takes back any earlier unsubscribe of them; `*` restores all); unsubscribe removes them
(subscribed to all, all but those, vehicles seen later included). A binary frame or a bad
message gets an error and the connection stays open.
Protocol version 2 (`?v=2`; the default, 1, is the above) sends what changed: a `live`
event's `data` is `{"slot", "changed": {field: value}}`, the fields of the slot that differ
from what this connection last sent of it (`{"slot", "fields"}`, the whole slot, the first
time and when a field went away), a `status_change`'s is `{"changed": {flag: value}}` (or
`{"flags"}`, every flag, likewise), and either carries `"diagnosis": {"condition", "text"}`
when the unit's diagnosis changed. The flags are the unit's `status` slot: a `status_change`
updates it as a `live` message of that slot does, and the next of either is diffed from both.
Every snapshot's units carry their `diagnosis` in both versions.
A client whose messages wait for more than `ws_control_queue` replies is closed (1008), and
a client that falls `ws_queue` events behind gets `{"type": "error", "reason": ...}` and is
closed with code 1008: it never slows the ingest or other clients. The key is checked again
every `KEY_RECHECK_S` through the authenticator's cache (no cost per event): once it is
revoked (within `KEY_RECHECK_S` in the revoking process, which drops the cache; within the
cache's TTL plus that when revoked by another process) the client gets an error and close
code 4401. Snapshots and events are only ever of vehicles in the key's scope, whatever the
client subscribes to. A key holds at most `ws_max_per_key` sockets open and a client address
at most `ws_max_per_client`: the next gets an error and close code 4429.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from collections.abc import Awaitable, Callable, Coroutine
from dataclasses import dataclass
from enum import StrEnum
from typing import Any
from urllib.parse import urlsplit

import orjson
from fastapi import APIRouter, WebSocket, WebSocketDisconnect

from eqgw.describe import describe
from eqgw.fleet.diagnosis import diagnose
from eqgw.ingest import events
from eqgw.ingest.events import Event
from eqgw.ingest.hub import SubscriberLagged, Subscription
from eqgw.ingest.state import vehicle_status
from eqgw.security.auth import authenticate, authenticate_session, session_cookie
from eqgw.security.keys import Scope
from eqgw.tasks import Backoff, cancel_and_wait, classify
from eqgw.web.responses import dumps
from eqgw.web.runtime import Runtime

router = APIRouter()
log = logging.getLogger(__name__)

WS_KINDS = events.UNIT_KINDS | events.ALERT_KINDS
CLOSE_UNAUTHORIZED = 4401
CLOSE_SLOW = 1008
# The server cannot tell whether the connection's credentials still hold (a bug): the client
# may connect again (its credentials are checked afresh then).
CLOSE_INTERNAL = 1011
CHECK_BROKEN_REASON = "the server cannot re-check this connection's credentials"
# Refused for a bound on open websockets (as HTTP's 429): per key, or per client address.
CLOSE_TOO_MANY = 4429
# How often an open connection's key is checked again (a cache hit: no I/O, but the cache
# expires every `key_cache_s`, and a revocation in this process drops it at once).
KEY_RECHECK_S = 1.0
# While the re-check fails (the database away), it is tried less often, up to this.
KEY_RECHECK_MAX_S = 15.0
# How long a connection without credentials waits for an `auth` first message.
AUTH_WAIT_S = 5.0
REVOKED_REASON = "the API key was revoked or is no longer valid"


class ClientMessage(StrEnum):
    """The `type`s of message a client sends (any other is answered with an error)."""

    AUTH = "auth"  # the key, as the first message of a connection without credentials
    SUBSCRIBE = "subscribe"  # add vehicles ("*": all of the key's scope); their snapshots come
    UNSUBSCRIBE = "unsubscribe"  # remove vehicles


class _Selection:
    """The vehicles a client wants: `vehicles`, or (None) every vehicle but `excluded`;
    never one outside its key's scope."""

    def __init__(self, vehicles: set[str] | None, scope: Scope) -> None:
        self.vehicles = vehicles
        self.excluded: set[str] = set()
        self.scope = scope

    def wants(self, event: Event) -> bool:
        vid = event.unit.vehicle_id
        if not self.scope.allows(vid):
            return False
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


def _event_message(event: Event, data: dict[str, Any] | None = None) -> bytes:
    return dumps(
        {
            "type": event.kind,
            "vehicle_id": event.unit.vehicle_id,
            "bus": event.unit.bus,
            "unit": event.unit.sa,
            "ts": event.ts,
            "data": event.data if data is None else data,
        }
    )


# The protocol versions a client may ask for with `?v=`: 1 sends every event's data whole, 2
# what changed.
VERSIONS = ("1", "2")
_DIAGNOSED_SLOTS = frozenset({"voltages", "status"})


def _diagnosis(voltages: dict[str, Any] | None, flags: dict[str, Any] | None) -> dict[str, str]:
    d = diagnose(voltages or None, flags)
    return {"condition": d["condition"], "text": d["text"]}


class _Sent:
    """What one connection of protocol 2 has been sent of each unit: every live slot's fields
    and the diagnosis. An event goes out as what changed since (the client merges it)."""

    def __init__(self) -> None:
        # (vehicle, bus, sa) -> slot -> fields as last sent (the event's own dict: no copy)
        self.slots: dict[tuple[str, str, int], dict[str, dict[str, Any]]] = {}
        self.diagnosis: dict[tuple[str, str, int], dict[str, str]] = {}

    def seed(self, vehicle_id: str, units: list[dict[str, Any]]) -> None:
        """A snapshot of the vehicle went out: its units' state starts from it."""
        for u in units:
            key = (vehicle_id, u["bus"], u["sa"])
            self.slots[key] = {slot: v["fields"] for slot, v in u["latest"].items()}
            self.diagnosis[key] = u["diagnosis"]

    def forget(self, vehicles: set[str] | None) -> None:
        """The client no longer follows `vehicles` (None: any)."""
        for table in (self.slots, self.diagnosis):
            for key in [k for k in table if vehicles is None or k[0] in vehicles]:
                del table[key]

    def message(self, event: Event) -> bytes:
        """The event as protocol 2 sends it: a live slot's or the status flags' changes."""
        kind = event.kind
        if kind != events.LIVE and kind != events.STATUS_CHANGE:
            return _event_message(event)
        ref = event.unit
        key = (ref.vehicle_id, ref.bus, ref.sa)
        slots = self.slots.setdefault(key, {})
        if kind == events.LIVE:
            slot = event.data.get("slot")
            fields = event.data.get("fields")
            if not isinstance(slot, str) or not isinstance(fields, dict):
                return _event_message(event)
        else:
            slot, fields = "status", event.data.get("flags")
            if not isinstance(fields, dict):
                return _event_message(event)
        before = slots.get(slot)
        slots[slot] = fields
        data: dict[str, Any]
        changed = (
            None
            if before is None or not before.keys() <= fields.keys()
            else {k: v for k, v in fields.items() if k not in before or before[k] != v}
        )
        if kind == events.STATUS_CHANGE:
            data = {"flags": fields} if changed is None else {"changed": changed}
        elif changed is None:
            data = {"slot": slot, "fields": fields}
        else:
            data = {"slot": slot, "changed": changed}
        if slot in _DIAGNOSED_SLOTS:
            now = _diagnosis(slots.get("voltages"), slots.get("status"))
            if self.diagnosis.get(key) != now:
                self.diagnosis[key] = now
                data["diagnosis"] = now
        return _event_message(event, data)


def _snapshot_units(live: Any, vehicle_id: str) -> list[dict[str, Any]]:
    """The vehicle's units as a snapshot shows them: live state and diagnosis."""
    units: list[dict[str, Any]] = live.snapshot(vehicle_id)
    for u in units:
        latest = u["latest"]
        voltages = latest.get("voltages")
        status = latest.get("status")
        u["diagnosis"] = _diagnosis(
            voltages["fields"] if voltages else None, status["fields"] if status else None
        )
    return units


@dataclass(frozen=True, slots=True)
class _Snapshot:
    """A vehicle's snapshot message and the units it holds (protocol 2 diffs from them once
    it is sent: in order with the events, never when it is made)."""

    vehicle_id: str
    units: list[dict[str, Any]]
    body: bytes


def _snapshots(rt: Runtime, vehicles: set[str] | None, scope: Scope) -> list[_Snapshot]:
    """Snapshots of `vehicles` (None: all) in `scope` (no default: every caller says whose
    key asks): a vehicle outside it is left out, as one that does not exist would be."""
    live = rt.ingest.live
    ids = (
        sorted(
            {u.ref.vehicle_id for u in live.units.values()} | {v.id for v in rt.settings.vehicles}
        )
        if vehicles is None
        else sorted(vehicles)
    )
    ids = [vid for vid in ids if scope.allows(vid)]
    now, after = time.time(), rt.settings.monitor.not_reporting_after_s
    out = []
    for vid in ids:
        units = _snapshot_units(live, vid)
        body = dumps(
            {
                "type": "snapshot",
                "vehicle_id": vid,
                "vehicle": vehicle_status(live.of_vehicle(vid), now, after).to_dict(),
                "units": units,
            }
        )
        out.append(_Snapshot(vid, units, body))
    return out


# One item per client message: error replies, or a subscribe's snapshots.
_Reply = list[bytes | _Snapshot]


def _send_text(item: bytes | _Snapshot, sent: _Sent | None) -> str:
    """The text of one reply to send now (a snapshot seeds what a protocol 2 client holds)."""
    if isinstance(item, _Snapshot):
        if sent is not None:
            sent.seed(item.vehicle_id, item.units)
        return item.body.decode()
    return item.decode()


class _Flooded(Exception):
    """The client sent requests faster than their replies could go out."""


def _enqueue(control: asyncio.Queue[_Reply], item: _Reply) -> None:
    try:
        control.put_nowait(item)
    except asyncio.QueueFull:
        raise _Flooded from None


def _same_origin(ws: WebSocket, rt: Runtime) -> bool:
    """Whether the handshake comes from a page of this gateway (a cookie is sent by the
    browser whichever page opens the socket; another site's page must not ride on it): the
    Origin's host is the one the request was sent to, or that of `EQGW_API_PUBLIC_URL` (a
    reverse proxy that rewrites Host)."""
    origin = ws.headers.get("origin")
    if origin is None:
        return True  # not a browser
    ours = {ws.headers.get("host", "").lower()}
    if rt.api.public_url:
        ours.add(urlsplit(rt.api.public_url).netloc.lower())
    return urlsplit(origin).netloc.lower() in ours


async def _first_message_key(ws: WebSocket) -> str | None:
    """The key of an `{"type": "auth", "key": ...}` first message, within AUTH_WAIT_S."""
    try:
        async with asyncio.timeout(AUTH_WAIT_S):
            message = await ws.receive()
    except (TimeoutError, WebSocketDisconnect, RuntimeError):
        return None
    try:
        msg = orjson.loads(message.get("text") or "")
    except orjson.JSONDecodeError:
        return None
    if (
        isinstance(msg, dict)
        and msg.get("type") == ClientMessage.AUTH
        and isinstance(msg.get("key"), str)
    ):
        return str(msg["key"])
    return None


class OpenWebsockets:
    """The websockets open per client address and per key, each bounded (settings
    `ws_max_per_client`, `ws_max_per_key`): one client cannot hold the event loop with
    hundreds of sockets. Counted on the event loop alone, so no lock."""

    def __init__(self) -> None:
        self.by_client: dict[str, int] = {}
        self.by_key: dict[int, int] = {}

    @staticmethod
    def take(table: dict[Any, int], who: Any, limit: int) -> bool:
        """Count one more socket of `who`, unless it holds `limit` already (False)."""
        held = table.get(who, 0)
        if held >= limit:
            return False
        table[who] = held + 1
        return True

    @staticmethod
    def give_back(table: dict[Any, int], who: Any) -> None:
        held = table.get(who, 0) - 1
        if held > 0:
            table[who] = held
        else:
            table.pop(who, None)


async def _refuse_too_many(ws: WebSocket, limit: str, reason: str, *, accept: bool = False) -> None:
    """Tell a socket why it is refused, close it (4429) and count it (a client gone in the
    meantime is no error)."""
    ws.app.state.metrics.ws_refused.labels(limit).inc()
    with contextlib.suppress(Exception):
        if accept:
            await ws.accept()
        await ws.send_text(dumps({"type": "error", "reason": reason}).decode())
        await ws.close(CLOSE_TOO_MANY, reason)


@router.websocket("/api/v1/ws")
async def websocket(ws: WebSocket) -> None:
    rt: Runtime = ws.app.state.rt
    sockets: OpenWebsockets = ws.app.state.open_websockets
    # Counted from the handshake on: sockets waiting for their `auth` message count too.
    address = ws.client.host if ws.client is not None else ""
    limit = rt.api.ws_max_per_client
    if not sockets.take(sockets.by_client, address, limit):
        reason = f"too many websockets open from this address ({limit}): close one first"
        await _refuse_too_many(ws, "client", reason, accept=True)
        return
    try:
        await _serve(ws, rt, sockets)
    finally:
        sockets.give_back(sockets.by_client, address)


async def _serve(ws: WebSocket, rt: Runtime, sockets: OpenWebsockets) -> None:
    """Authenticate the socket, then serve it within its key's bound."""
    token = ws.query_params.get("key")
    auth = ws.headers.get("authorization", "")
    if not token and auth.lower().startswith("bearer "):
        token = auth[7:].strip()
    cookie = None if token else session_cookie(ws.headers)
    principal = None
    if cookie is not None:
        session = await authenticate_session(rt, cookie) if _same_origin(ws, rt) else None
        principal = session.principal if session is not None else None
    elif token:
        principal = await authenticate(rt, token)
    await ws.accept()
    if cookie is None and not token:
        token = await _first_message_key(ws)
        principal = await authenticate(rt, token)
    if principal is None or not principal.allows("viewer"):  # an ingest key reads nothing
        await ws.send_text('{"type":"error","reason":"a valid API key is required"}')
        await ws.close(CLOSE_UNAUTHORIZED, "unauthorized")
        return
    limit = rt.api.ws_max_per_key
    if not sockets.take(sockets.by_key, principal.key_id, limit):
        reason = f"too many websockets open for this key ({limit}): close one first"
        await _refuse_too_many(ws, "key", reason)
        return
    try:
        await _stream(ws, rt, principal.scope, token, cookie)
    finally:
        sockets.give_back(sockets.by_key, principal.key_id)


async def _stream(
    ws: WebSocket, rt: Runtime, scope: Scope, token: str | None, cookie: str | None
) -> None:
    """Snapshots, then events and the replies to the client's messages, until it leaves, falls
    behind, floods, or its key or session ends."""
    try:
        selection = _Selection(_parse_vehicles(ws.query_params.get("vehicles")), scope)
    except ValueError as exc:
        await ws.close(1003, str(exc))
        return
    version = ws.query_params.get("v", "1")
    if version not in VERSIONS:
        await ws.close(1003, f"v is one of {', '.join(VERSIONS)}")
        return
    sent = _Sent() if version == "2" else None
    maxsize = rt.api.ws_queue
    subs: list[Subscription] = [
        rt.ingest.hub.subscribe(WS_KINDS, maxsize=maxsize, predicate=selection.wants),
        rt.commands.hub.subscribe(None, maxsize=maxsize, predicate=selection.wants),
    ]
    # One item per client message (a subscribe's snapshots together): a client sending
    # faster than its replies go out is closed, never buffered without bound.
    control: asyncio.Queue[_Reply] = asyncio.Queue(maxsize=rt.api.ws_control_queue)
    try:
        # Snapshots go out before any event, so a client never starts blank.
        for snap in _snapshots(rt, selection.vehicles, selection.scope):
            await ws.send_text(_send_text(snap, sent))
    except (WebSocketDisconnect, RuntimeError):
        for sub in subs:
            sub.close()
        return
    reader = asyncio.create_task(_read_client(ws, rt, selection, control, sent))
    watcher = asyncio.create_task(
        _watch_session(rt, cookie) if cookie is not None else _watch_key(rt, token)
    )
    connected = ws.app.state.metrics.websockets
    connected.inc()
    try:
        await _pump(ws, rt, subs, control, reader, watcher, sent)
    finally:
        connected.dec()
        for task in (reader, watcher):
            await cancel_and_wait(task, quiet=True)
        for sub in subs:
            sub.close()


async def _read_client(
    ws: WebSocket,
    rt: Runtime,
    selection: _Selection,
    control: asyncio.Queue[_Reply],
    sent: _Sent | None,
) -> str | None:
    """Handle subscribe/unsubscribe messages; ends when the client goes away (None) or
    floods (the reason to close it)."""
    try:
        while True:
            try:
                message = await ws.receive()
            except (WebSocketDisconnect, RuntimeError):
                return None
            if message["type"] == "websocket.disconnect":
                return None
            raw = message.get("text")
            if raw is None:
                reason = "binary frames are not understood: send JSON text frames"
                _enqueue(control, [dumps({"type": "error", "reason": reason})])
                continue
            try:
                msg = orjson.loads(raw)
                kind = msg.get("type")
                vehicles = _parse_vehicles(msg.get("vehicles", "*"))
            except (orjson.JSONDecodeError, AttributeError, ValueError) as exc:
                _enqueue(control, [dumps({"type": "error", "reason": f"bad message: {exc}"})])
                continue
            if kind == ClientMessage.SUBSCRIBE:
                added = selection.subscribe(vehicles)
                _enqueue(control, list(_snapshots(rt, added, selection.scope)))
            elif kind == ClientMessage.UNSUBSCRIBE:
                selection.unsubscribe(vehicles)
                if sent is not None:
                    sent.forget(vehicles)
            else:
                _enqueue(control, [dumps({"type": "error", "reason": f"unknown type {kind!r}"})])
    except _Flooded:
        return f"too many messages: {rt.api.ws_control_queue} replies waiting"


async def _watch(check: Callable[[], Awaitable[str | None]], what: str) -> str:
    """Run `check` every `KEY_RECHECK_S` until it says why the connection's credentials no
    longer hold (a revoked or expired key, a logout), and return that.

    A check is a hit in the authenticator's cache (no I/O) unless the cache expired or was
    dropped by a revocation in this process, so it costs nothing per event.
    """
    backoff = Backoff(KEY_RECHECK_S, KEY_RECHECK_MAX_S)
    delay = KEY_RECHECK_S
    while True:
        await asyncio.sleep(delay)
        try:
            reason = await check()
        except Exception as exc:
            fault = classify(exc)
            if not fault.heals:  # a bug: no retry answers it; the client may connect again
                log.error(
                    "websocket %s re-check failed (%s), closing the connection: %s",
                    what,
                    fault.reason,
                    describe(exc),
                    exc_info=exc,
                )
                return CHECK_BROKEN_REASON
            # The database unreachable is no revocation: check again, less often meanwhile.
            if not backoff.failures:
                log.warning("websocket %s re-check failed: %s", what, describe(exc))
            delay = backoff.next()
            continue
        backoff.reset()
        delay = KEY_RECHECK_S
        if reason is not None:
            return reason


def _watch_key(rt: Runtime, token: str | None) -> Coroutine[Any, Any, str]:
    """Ends with the reason once the connection's key no longer reads the fleet."""

    async def check() -> str | None:
        principal = await authenticate(rt, token)
        if principal is None:
            return REVOKED_REASON
        if not principal.allows("viewer"):
            return f"the {principal.role} role cannot read the fleet"
        return None

    return _watch(check, "key")


def _watch_session(rt: Runtime, cookie: str) -> Coroutine[Any, Any, str]:
    """Ends with the reason once the connection's session cookie ends (a logout, or its key
    revoked or expired)."""

    async def check() -> str | None:
        if await authenticate_session(rt, cookie) is None:
            return "the session ended (logged out, expired, or its key was revoked)"
        return None

    return _watch(check, "session")


async def _pump(
    ws: WebSocket,
    rt: Runtime,
    subs: list[Subscription],
    control: asyncio.Queue[_Reply],
    reader: asyncio.Task[str | None],
    watcher: asyncio.Task[str],
    sent: _Sent | None,
) -> None:
    """Send snapshots and events in order until the client leaves or falls behind, or its
    key is revoked."""
    timeout = rt.api.ws_send_timeout_s
    encode = _event_message if sent is None else sent.message
    getters: dict[asyncio.Future[Any], Any] = {asyncio.ensure_future(control.get()): control}
    for sub in subs:
        getters[asyncio.ensure_future(sub.get())] = sub
    getters[reader] = None
    getters[watcher] = None
    try:
        while True:
            done, _ = await asyncio.wait(getters, return_when=asyncio.FIRST_COMPLETED)
            if reader in done:
                flooded = reader.result()
                if flooded is not None:
                    with contextlib.suppress(Exception):
                        async with asyncio.timeout(timeout):
                            await ws.send_text(dumps({"type": "error", "reason": flooded}).decode())
                            await ws.close(CLOSE_SLOW, flooded)
                return  # the client left, or floods
            if watcher in done:
                reason = watcher.result()
                code = CLOSE_INTERNAL if reason == CHECK_BROKEN_REASON else CLOSE_UNAUTHORIZED
                with contextlib.suppress(Exception):
                    async with asyncio.timeout(timeout):
                        await ws.send_text(dumps({"type": "error", "reason": reason}).decode())
                        await ws.close(code, reason)
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
                batch: _Reply = item if isinstance(item, list) else [encode(item)]
                try:
                    for data in batch:
                        async with asyncio.timeout(timeout):
                            await ws.send_text(_send_text(data, sent))
                except (TimeoutError, WebSocketDisconnect, RuntimeError):
                    return
                # Drain what is already queued without a round through asyncio.wait.
                if isinstance(source, Subscription):
                    while (more := _next_nowait(source)) is not None:
                        async with asyncio.timeout(timeout):
                            await ws.send_text(encode(more).decode())
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
