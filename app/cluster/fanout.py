"""Hub events shared between gateways through PostgreSQL LISTEN/NOTIFY.

Each gateway publishes the events of its own buses (live values, status and fault changes,
units online) and of the commands it handles; the others republish them in their hubs as
`RemoteEvent`s, which are never sent on again. Notifications are batched into payloads under
PostgreSQL's 8000-byte limit.

Any database role may NOTIFY on any channel and the channel's name is no secret, so every
payload is sealed: an HMAC-SHA256 with a secret kept in the `cluster_secrets` table (made by
the first gateway; a role without privileges on the gateway's tables cannot read it), over
the sender's boot id, a sequence number and the send time. A payload whose seal is wrong, that
is older than `MAX_AGE_S`, or whose sequence number was seen already (a replay) is dropped and
counted (`rejected` in /readyz's cluster status).

Notifications are not durable: a gateway whose listening connection drops reloads the other
gateways' units from the database when it is back (`on_resync`).
"""

from __future__ import annotations

import asyncio
import contextlib
import hashlib
import hmac
import logging
import secrets
import time
from collections.abc import Awaitable, Callable, Iterable
from dataclasses import dataclass
from typing import Any

import orjson
import psycopg

from eqgw.ingest import events
from eqgw.ingest.events import Event, UnitRef
from eqgw.ingest.hub import EventHub, SubscriberLagged, Subscription
from eqgw.supervisor import Supervisor, spawn
from eqgw.tasks import Backoff, cancel_and_wait, heals

log = logging.getLogger(__name__)

COMMAND_KIND = "command"
FLEET_KIND = "fleet"  # a change of the fleet's vehicles and buses (eqgw.fleet.sync)
PAYLOAD_LIMIT = 7900  # NOTIFY takes less than 8000 bytes
RECONNECT_S = (0.5, 10.0)
SEAL_OVERHEAD = 128  # "s1.<boot>.<seq>.<ts>.<mac>." before the JSON
MAX_AGE_S = 30.0  # a sealed payload older than this (by the sender's clock) is refused


class Sealer:
    """Seals this gateway's payloads and checks the others' (see the module's docstring)."""

    def __init__(self, secret: str) -> None:
        self.key = secret.encode()
        self.boot = secrets.token_hex(8)
        self.seq = 0
        self._last: dict[str, int] = {}  # sender's boot -> last sequence number accepted

    def _mac(self, head: str, body: str) -> str:
        return hmac.new(self.key, head.encode() + body.encode(), hashlib.sha256).hexdigest()

    def seal(self, body: str, now: float | None = None) -> str:
        self.seq += 1
        head = f"s1.{self.boot}.{self.seq}.{int((now or time.time()) * 1000)}."
        return f"{head}{self._mac(head, body)}.{body}"

    def open(self, payload: str, now: float | None = None) -> str | None:
        """The JSON of a genuine, fresh, first-seen payload; None otherwise."""
        parts = payload.split(".", 5)
        if len(parts) != 6 or parts[0] != "s1":
            return None
        _, boot, seq_s, ts_s, mac, body = parts
        head = f"s1.{boot}.{seq_s}.{ts_s}."
        if not hmac.compare_digest(mac, self._mac(head, body)):
            return None
        try:
            seq, ts = int(seq_s), int(ts_s) / 1000
        except ValueError:
            return None
        if abs((now or time.time()) - ts) > MAX_AGE_S or seq <= self._last.get(boot, 0):
            return None
        if len(self._last) > 10_000:
            self._last.clear()
        self._last[boot] = seq
        return body


@dataclass(frozen=True, slots=True)
class RemoteEvent(Event):
    """An event that happened on another gateway (`origin`), republished here."""

    origin: str = ""


def is_remote(event: Event) -> bool:
    """Whether another gateway produced this event (subscribers that act on events, such as
    alert rules, should act on local ones only: the owner of the bus acts)."""
    return isinstance(event, RemoteEvent)


def _local(event: Event) -> bool:
    return not isinstance(event, RemoteEvent)


def encode_batches(origin: str, evs: Iterable[Event], limit: int = PAYLOAD_LIMIT) -> list[str]:
    """Events packed into JSON payloads of at most `limit` bytes; an event too large on its
    own is left out (returned payloads never exceed the limit)."""
    head = orjson.dumps(origin).decode()
    out: list[str] = []
    parts: list[str] = []
    size = 0
    base = len(head) + 12  # {"o":...,"e":[...]}
    for ev in evs:
        item = orjson.dumps(
            [ev.kind, ev.unit.vehicle_id, ev.unit.bus, ev.unit.sa, ev.ts, ev.data],
            option=orjson.OPT_NON_STR_KEYS,
            default=str,
        ).decode()
        if base + len(item.encode()) > limit:
            log.warning("fan-out: a %s event of %s is too large to share", ev.kind, ev.unit.bus)
            continue
        if parts and base + size + len(parts) + len(item.encode()) > limit:
            out.append(f'{{"o":{head},"e":[{",".join(parts)}]}}')
            parts, size = [], 0
        parts.append(item)
        size += len(item.encode())
    if parts:
        out.append(f'{{"o":{head},"e":[{",".join(parts)}]}}')
    return out


def decode_batch(payload: str) -> tuple[str, list[RemoteEvent]]:
    """(origin, events) of one notification payload."""
    msg = orjson.loads(payload)
    origin = str(msg["o"])
    out = [
        RemoteEvent(kind, UnitRef(vid, bus, int(sa)), float(ts), data or {}, origin=origin)
        for kind, vid, bus, sa, ts, data in msg["e"]
    ]
    return origin, out


@dataclass(slots=True)
class FanOutStats:
    """Counters of the fan-out."""

    published: int = 0
    notifications: int = 0
    received: int = 0
    lost: int = 0  # local events not shared (subscriber lagged, database away)
    reconnects: int = 0
    rejected: int = 0  # notifications whose seal was wrong, stale or replayed


class FanOut:
    """Publishes this gateway's events to the others and republishes theirs here."""

    def __init__(
        self,
        conninfo: str,
        channel: str,
        instance_id: str,
        ingest_hub: EventHub,
        command_hub: EventHub,
        *,
        on_remote: Callable[[RemoteEvent], bool],
        on_resync: Callable[[], Awaitable[None]],
        queue_size: int = 20_000,
        supervisor: Supervisor | None = None,
    ) -> None:
        self.supervisor = supervisor  # owns the tasks when given (see ClusterNode)
        self.conninfo = conninfo
        self.channel = channel
        self.instance_id = instance_id
        self.ingest_hub = ingest_hub
        self.command_hub = command_hub
        self.on_remote = on_remote
        self.on_resync = on_resync
        self.queue_size = queue_size
        self.stats = FanOutStats()
        self.listening = False
        self._tasks: list[asyncio.Task[None]] = []
        self._notify_conn: psycopg.AsyncConnection[tuple[object, ...]] | None = None
        self._send_lock = asyncio.Lock()
        self._listening_now = asyncio.Event()
        self.sealer: Sealer | None = None

    async def start(self, *, wait: float = 5.0) -> None:
        """Start listening and publishing; waits up to `wait` s for the first LISTEN."""
        self.sealer = Sealer(await self._secret())
        sup = self.supervisor
        self._tasks = [
            spawn(sup, "fan-out listen", self._listen),
            # What other gateways' websockets and mirrors need; `record` stays local.
            spawn(sup, "fan-out ingest", lambda: self._publish(self.ingest_hub, events.UNIT_KINDS)),
            spawn(sup, "fan-out commands", lambda: self._publish(self.command_hub, None)),
        ]
        with contextlib.suppress(TimeoutError):
            async with asyncio.timeout(wait):
                await self._listening_now.wait()

    async def stop(self) -> None:
        tasks, self._tasks = self._tasks, []
        for task in tasks:
            await cancel_and_wait(task)
        conn, self._notify_conn = self._notify_conn, None
        if conn is not None:
            with contextlib.suppress(Exception):
                await conn.close()

    def status(self) -> dict[str, Any]:
        s = self.stats
        return {
            "channel": self.channel,
            "listening": self.listening,
            "published": s.published,
            "notifications": s.notifications,
            "received": s.received,
            "lost": s.lost,
            "reconnects": s.reconnects,
            "rejected": s.rejected,
        }

    async def _secret(self) -> str:
        """The cluster's signing secret (created by the first gateway to need it)."""
        conn = await self._connect("secret")
        try:
            await conn.execute(
                "INSERT INTO cluster_secrets (id, secret, created_at) VALUES (1, %s, %s) "
                "ON CONFLICT (id) DO NOTHING",
                (secrets.token_hex(32), time.time()),
            )
            cur = await conn.execute("SELECT secret FROM cluster_secrets WHERE id = 1")
            row = await cur.fetchone()
        finally:
            await conn.close()
        assert row is not None
        return str(row[0])

    async def announce(self, kind: str, data: dict[str, Any]) -> None:
        """Tell the other gateways of something that is no unit's event (a fleet change:
        eqgw.fleet.sync), sealed like every payload; raises when it cannot be sent."""
        assert self.sealer is not None
        event = Event(kind, UnitRef("", "", 0), time.time(), data)
        sealer = self.sealer
        limit = PAYLOAD_LIMIT - SEAL_OVERHEAD
        await self._send([sealer.seal(p) for p in encode_batches(self.instance_id, [event], limit)])

    # -- out --------------------------------------------------------------------------------

    async def _connect(self, name: str) -> psycopg.AsyncConnection[tuple[object, ...]]:
        return await psycopg.AsyncConnection.connect(
            self.conninfo,
            autocommit=True,
            connect_timeout=5,
            application_name=f"eqgw-fanout:{self.instance_id}:{name}"[:63],
        )

    async def _send(self, payloads: list[str]) -> None:
        async with self._send_lock:
            if self._notify_conn is None or self._notify_conn.closed:
                self._notify_conn = await self._connect("notify")
            # One statement, one transaction: the batch is delivered in order, at once.
            await self._notify_conn.execute(
                "SELECT pg_notify(%s, p) FROM unnest(%s::text[]) AS p", (self.channel, payloads)
            )

    async def _publish(self, hub: EventHub, kinds: frozenset[str] | None) -> None:
        backoff = Backoff(*RECONNECT_S)
        while True:
            sub: Subscription = hub.subscribe(kinds, maxsize=self.queue_size, predicate=_local)
            with sub:
                try:
                    while True:
                        first = await sub.get()
                        batch = [first]
                        while len(batch) < 5000 and (more := sub.get_nowait()) is not None:
                            batch.append(more)
                        assert self.sealer is not None
                        payloads = [
                            self.sealer.seal(p)
                            for p in encode_batches(
                                self.instance_id, batch, PAYLOAD_LIMIT - SEAL_OVERHEAD
                            )
                        ]
                        try:
                            await self._send(payloads)
                            backoff.reset()
                        except (psycopg.Error, OSError) as exc:
                            if not heals(exc):
                                raise  # a refused login: its owner stops it
                            self.stats.lost += len(batch)
                            log.warning("fan-out: %d events not shared: %s", len(batch), exc)
                            await self._drop_notify_conn()
                            await asyncio.sleep(backoff.next())
                            continue
                        self.stats.published += len(batch)
                        self.stats.notifications += len(payloads)
                except SubscriberLagged:
                    self.stats.lost += self.queue_size
                    log.warning(
                        "fan-out fell %d events behind; some were not shared", self.queue_size
                    )
                except StopAsyncIteration:
                    return  # the hub closed

    async def _drop_notify_conn(self) -> None:
        conn, self._notify_conn = self._notify_conn, None
        if conn is not None:
            with contextlib.suppress(Exception):
                await conn.close()

    # -- in ---------------------------------------------------------------------------------

    async def _listen(self) -> None:
        backoff = Backoff(*RECONNECT_S)
        while True:
            conn = None
            try:
                conn = await self._connect("listen")
                await conn.execute(f'LISTEN "{self.channel}"')
                self.listening = True
                self._listening_now.set()
                # Whatever was missed while not listening is in the database.
                await self.on_resync()
                backoff.reset()
                async for note in conn.notifies():
                    self._deliver(note.payload)
            except (psycopg.Error, OSError) as exc:
                if not heals(exc):
                    raise  # a refused login: its owner stops it
                log.warning(
                    "fan-out listener lost (%s); retrying in about %.1f s", exc, backoff.delay
                )
            finally:
                self.listening = False
                if conn is not None:
                    with contextlib.suppress(Exception):
                        await conn.close()
            self.stats.reconnects += 1
            await asyncio.sleep(backoff.next())

    def _deliver(self, payload: str) -> None:
        assert self.sealer is not None
        body = self.sealer.open(payload)
        if body is None:
            self.stats.rejected += 1
            if self.stats.rejected == 1 or self.stats.rejected % 1000 == 0:
                log.warning(
                    "fan-out: %d notifications refused (not sealed by a gateway, stale or "
                    "replayed): some database role is sending on %s",
                    self.stats.rejected,
                    self.channel,
                )
            return
        try:
            origin, evs = decode_batch(body)
        except (orjson.JSONDecodeError, KeyError, TypeError, ValueError) as exc:
            log.warning("fan-out: unreadable notification (%s)", exc)
            return
        if origin == self.instance_id:
            return
        for ev in evs:
            self.stats.received += 1
            if not self.on_remote(ev):
                continue
            hub = self.command_hub if ev.kind == COMMAND_KIND else self.ingest_hub
            hub.publish(ev)
