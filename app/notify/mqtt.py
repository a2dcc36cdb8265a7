"""Alert events to an MQTT broker, from the same outbox as the webhooks, with its own cursor.

Each event is published at QoS 1 (by default) to `<topic_prefix>/<vehicle_id>/<rule>` with the
webhook JSON body as payload; the cursor moves past an event only once the broker acknowledged
it, so nothing is lost while the broker is away (at least once: a lost ack means a resend).
paho-mqtt's network thread connects and reconnects with backoff; the asyncio side only reads
plain attributes it sets. With several gateways on one database a lease on the cursor row lets
one publish at a time.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
import uuid
from collections import Counter
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import orjson
import paho.mqtt.client as paho
from paho.mqtt.enums import CallbackAPIVersion
from sqlalchemy import Connection, Engine

from eqgw.describe import describe
from eqgw.notify import repository as q
from eqgw.notify.webhooks import event_body
from eqgw.store.transaction import R, in_transaction
from eqgw.tasks import Backoff, cancel_and_wait, classify

if TYPE_CHECKING:
    from eqgw.config import DeliverySettings, MqttSettings

log = logging.getLogger(__name__)

BATCH = 200
# A publish round that fails (the database away) is tried again after a delay doubling up to this.
RETRY_MAX_S = 10.0
TARGET_NAME = "mqtt"  # the name a rule's `targets` lists to send its alerts here


def topic_level(value: Any) -> str:
    """A name as one topic level: MQTT's separator and wildcards in it made harmless."""
    text = str(value) if value not in (None, "") else "unknown"
    return text.replace("/", "_").replace("+", "_").replace("#", "_")


def topic_for(prefix: str, alert: dict[str, Any]) -> str:
    """`prefix/vehicle/rule`, with MQTT's special characters in either name made harmless."""
    vehicle, rule = topic_level(alert.get("vehicle_id")), topic_level(alert.get("rule"))
    return f"{prefix.rstrip('/')}/{vehicle}/{rule}"


# CONNACK reason codes no reconnect cures (MQTT 5 numbering, which paho also gives for
# 3.1.1's answers): the client id, the user name or password, the authorisation, a ban.
REFUSED_FOR_GOOD = frozenset({133, 134, 135, 138, 140})


def refused_for_good(reason: Any) -> bool:
    """Whether a broker's CONNACK `reason` is a refusal a reconnect would only repeat."""
    return getattr(reason, "value", None) in REFUSED_FOR_GOOD


def give_up_connecting(client: Any, what: str, host: str | None, port: int, reason: Any) -> str:
    """A broker refused the credentials (paho's thread): said in one line, no more reconnects
    (paho would try for ever); the reason returned for the owner's status."""
    why = f"refused by the broker, not retried: {reason}"
    log.error("%s %s:%s: %s (check mqtt.username and mqtt.password)", what, host, port, why)
    with contextlib.suppress(Exception):
        client.disconnect()  # paho's network thread ends instead of reconnecting
    return why


def new_client(settings: MqttSettings, client_id: str) -> paho.Client:
    """A paho client for the broker of `settings`: MQTT 3.1.1, its credentials and TLS, and
    the reconnect backoff its network thread follows. The caller sets the callbacks (and a
    will), then connects; the alert publisher and the telemetry each have their own."""
    client = paho.Client(
        callback_api_version=CallbackAPIVersion.VERSION2,
        client_id=client_id,
        protocol=paho.MQTTv311,
    )
    if settings.username:
        client.username_pw_set(settings.username, settings.password)
    if settings.tls:
        client.tls_set()
    client.reconnect_delay_set(
        min_delay=max(1, round(settings.reconnect_min_s)),
        max_delay=max(1, round(settings.reconnect_max_s)),
    )
    return client


class MqttPublisher:
    """Publishes alert events past the `mqtt` cursor while connected."""

    def __init__(
        self,
        engine: Engine,
        settings: MqttSettings,
        delivery: DeliverySettings,
        public_url: str,
    ) -> None:
        # Every transaction here writes: on SQLite take the write lock up front (busy_timeout).
        self.engine = engine.execution_options(sqlite_begin="IMMEDIATE")
        self.settings = settings
        self.delivery = delivery
        self.public_url = public_url
        self.owner = f"mqtt-{uuid.uuid4().hex[:12]}"
        self.lease_s = settings.publish_timeout_s + 30.0
        self.counters: Counter[str] = Counter()
        self.connected = False
        self.last_error: str | None = None
        # Why it stopped for good (the broker refused its credentials, or a bug), else None.
        self.failed: str | None = None
        self._gaps: dict[int, float] = {}
        self._wake = asyncio.Event()
        self._task: asyncio.Task[None] | None = None
        self._client: paho.Client | None = None

    # -- paho callbacks (its network thread: plain attributes only) ---------------------------

    def _on_connect(self, client: Any, _u: Any, _flags: Any, reason: Any, _props: Any) -> None:
        if reason.is_failure:
            self.connected = False
            self.last_error = f"connection refused: {reason}"
            if refused_for_good(reason):
                s = self.settings
                self.failed = give_up_connecting(client, "MQTT", s.host, s.port, reason)
                return
            log.warning("MQTT %s:%s: %s", self.settings.host, self.settings.port, reason)
            return
        self.connected = True
        self.last_error = None
        log.info("MQTT connected to %s:%s", self.settings.host, self.settings.port)

    def _on_disconnect(self, _c: Any, _u: Any, _flags: Any, reason: Any, _props: Any) -> None:
        if self.connected:
            log.warning("MQTT disconnected from %s: %s", self.settings.host, reason)
        self.connected = False
        self.last_error = f"disconnected: {reason}"

    def _on_connect_fail(self, _c: Any, _u: Any) -> None:
        self.connected = False
        self.last_error = "cannot connect"

    # -- lifecycle -----------------------------------------------------------------------------

    async def start(self) -> None:
        s = self.settings
        client = new_client(s, s.client_id or f"eqgw-{uuid.uuid4().hex[:12]}")
        client.on_connect = self._on_connect
        client.on_disconnect = self._on_disconnect
        client.on_connect_fail = self._on_connect_fail
        await asyncio.to_thread(self.ensure_cursor)
        client.connect_async(s.host or "", s.port, keepalive=s.keepalive_s)
        client.loop_start()  # connects, and reconnects with backoff, on its own thread
        self._client = client
        self._task = asyncio.create_task(self._run(), name="mqtt alert publisher")

    def ensure_cursor(self) -> int:
        """The persisted `mqtt` cursor, created on the first start with a broker past the
        history but before every event of the alerts still open (worker thread). Called
        before the alert engine starts (`AlertDelivery.prepare`): nothing it raises is skipped."""
        return int(
            self._in_tx(
                lambda conn: q.ensure_cursor(
                    conn, q.MQTT_CURSOR, q.first_publish_position(conn), time.time()
                )
            )
        )

    async def stop(self) -> None:
        task, self._task = self._task, None
        if task is not None:
            await cancel_and_wait(task)
        with contextlib.suppress(Exception):
            await asyncio.to_thread(
                self._in_tx, lambda c: q.release_cursor_lease(c, q.MQTT_CURSOR, self.owner)
            )
        client, self._client = self._client, None
        if client is not None:
            client.disconnect()
            await asyncio.to_thread(client.loop_stop)
        self.connected = False

    def wake(self) -> None:
        self._wake.set()

    def _in_tx(self, fn: Callable[[Connection], R]) -> R:
        return in_transaction(self.engine, fn)

    async def _run(self) -> None:
        backoff = Backoff(self.delivery.poll_s, max(self.delivery.poll_s, RETRY_MAX_S))
        while self.failed is None:
            wait = self.delivery.poll_s
            try:
                n = await asyncio.to_thread(self.publish_round)
                backoff.reset()
            except Exception as exc:
                fault = classify(exc)
                self.counters["failures"] += 1
                if not fault.heals:  # a bug, or storage that will not heal: said once, ended
                    self.failed = f"{fault.reason}: {describe(exc)}"
                    log.error(
                        "MQTT alert publisher stopped, not retried: %s",
                        self.failed,
                        exc_info=exc if fault.bug else None,
                    )
                    return
                wait = backoff.next()
                if backoff.failures == 1 or backoff.failures % 10 == 0:
                    log.warning(
                        "MQTT publish round failed (%d in a row), retrying in %.1f s: %s",
                        backoff.failures,
                        wait,
                        exc,
                    )
                n = 0
            if n < BATCH:
                with contextlib.suppress(TimeoutError):
                    async with asyncio.timeout(wait):
                        await self._wake.wait()
                self._wake.clear()

    def publish_round(self) -> int:
        """Publish the events past the cursor and move it past those the broker acknowledged
        (worker thread). Returns how many events were read."""
        client = self._client
        if client is None or not self.connected or not client.is_connected():
            return 0
        now = time.time()

        def read(conn: Any) -> tuple[int, list[q.OutboxEvent]] | None:
            if not q.take_cursor_lease(conn, q.MQTT_CURSOR, self.owner, now, self.lease_s):
                return None  # another gateway publishes
            after = q.read_cursor(conn, q.MQTT_CURSOR)
            assert after is not None
            return after, q.events_after(conn, after, BATCH)

        got = self._in_tx(read)
        if got is None:
            return 0
        after, events = got
        events = events[
            : q.readable_count(
                after, [e.id for e in events], self._gaps, now, self.delivery.gap_wait_s
            )
        ]
        sent: list[tuple[int, paho.MQTTMessageInfo | None]] = []
        for event in events:
            if event.muted or (event.targets and TARGET_NAME not in event.targets):
                sent.append((event.id, None))
                continue
            body = event_body(event.payload, event.id, self.public_url)
            info = client.publish(
                topic_for(self.settings.topic_prefix, event.alert),
                orjson.dumps(body),
                qos=self.settings.qos,
            )
            if info.rc != paho.MQTT_ERR_SUCCESS:
                break
            sent.append((event.id, info))
        last = after
        deadline = time.monotonic() + self.settings.publish_timeout_s
        published = 0
        for event_id, pending in sent:
            if pending is not None:
                try:
                    pending.wait_for_publish(timeout=max(0.0, deadline - time.monotonic()))
                except (RuntimeError, ValueError):
                    break
                if not pending.is_published():
                    break
                published += 1
            last = event_id
        if last < (sent[-1][0] if sent else after):
            self.counters["failures"] += 1
        self.counters["published"] += published
        if last > after:
            self._in_tx(lambda c: q.advance_cursor(c, q.MQTT_CURSOR, last, time.time()))
        return len(events)
