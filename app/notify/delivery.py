"""Alert delivery: the webhook dispatcher (a persistent outbox with retries) and MQTT.

Every alert change appends a row to `alert_events` in the same transaction. The dispatcher reads
them past a cursor and queues one `webhook_deliveries` row per matching webhook (in one
transaction with the cursor's advance), then claims due rows, POSTs them signed and records each
attempt. A failing webhook is retried with exponential backoff and jitter, its other deliveries
wait behind the oldest, and one still failing after `give_up_after_s` (24 h) is marked failed and
logged. Rows, not memory: a restart, or another gateway on the same PostgreSQL, picks up
where it was. Delivery is at least once; receivers dedupe on the event id.

A claim is leased (`delivery.lease_s`); the gateway sending a run renews it before an attempt
would outlast it, and stops sending the run when it cannot (the database is away, or the lease
ran out and another gateway took the rest): no other gateway sends a run while its claimant is
alive and sending. Each attempt is bounded in all by `timeout_s`.
"""

from __future__ import annotations

import asyncio
import contextlib
import importlib
import logging
import sys
import time
import uuid
from collections import Counter
from collections.abc import Callable, Iterator
from typing import TYPE_CHECKING, Any, Concatenate

from prometheus_client import CollectorRegistry
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, Metric
from prometheus_client.registry import Collector
from sqlalchemy import Connection, Engine

from eqgw.describe import describe
from eqgw.notify import repository as q
from eqgw.notify.destinations import IPNetwork, parse_networks, redact_url
from eqgw.notify.senders import send
from eqgw.notify.webhooks import Attempt, event_body, test_payload
from eqgw.store.transaction import P, R, run_in_transaction
from eqgw.tasks import Backoff, backoff_delay, cancel_and_wait, classify, http_status_heals

if TYPE_CHECKING:
    import httpx

    from eqgw.config import DeliverySettings, Settings, SmtpSettings

log = logging.getLogger(__name__)
# How long stop() lets webhook attempts under way finish (inside the shutdown bound).
STOP_GRACE_S = 2.0

FAN_OUT_BATCH = 500
# While a run is sent, new events are fanned out and the undelivered ones counted this often.
STEP_REFRESH_S = 0.5
# A round that fails (the database away) is tried again after a delay doubling up to this.
ROUND_RETRY_MAX_S = 10.0


class WebhookDispatcher:
    """Fans alert events out to webhooks and delivers them, in a background task."""

    def __init__(
        self,
        engine: Engine,
        settings: DeliverySettings,
        public_url: str,
        allow: tuple[IPNetwork, ...] = (),
        smtp: SmtpSettings | None = None,
    ) -> None:
        self.allow = allow
        self.smtp = smtp
        # Every transaction here writes: on SQLite take the write lock up front (busy_timeout).
        self.engine = engine.execution_options(sqlite_begin="IMMEDIATE")
        self.settings = settings
        self.public_url = public_url
        self.counters: Counter[str] = Counter()
        self.pending = 0
        # Events not yet delivered nor failed, per webhook name (eqgw_webhook_pending).
        self.pending_by_hook: dict[str, int] = {}
        # Our own failure (a round: the database) and the receivers' latest, for /readyz.
        self.last_error: str | None = None
        self.last_attempt_error: dict[str, Any] | None = None
        # Why the dispatcher stopped for good (a bug, storage that will not heal), else None.
        self.failed: str | None = None
        # Webhooks whose receiver refuses deliveries for a reason no retry cures (HTTP 4xx
        # but 408/425/429: a wrong signature secret, a gone address): name -> its answer.
        self.refusing: dict[str, str] = {}
        # A claimed delivery is leased for longer than an attempt can take.
        self.lease_s = settings.claim_lease_s
        self._gaps: dict[int, float] = {}
        # Claimed deliveries not yet attempted: id -> the claim's lease time (its token).
        self._claimed: dict[int, float] = {}
        self._refresh_lock = asyncio.Lock()
        self._refreshed_at = 0.0
        self._stopping = False
        self._wake = asyncio.Event()
        self._client: httpx.AsyncClient | None = None
        self._task: asyncio.Task[None] | None = None

    async def start(self) -> None:
        self._stopping = False
        self._task = asyncio.create_task(self._run(), name="webhook delivery")

    async def stop(self) -> None:
        """Finish the attempts under way (up to the HTTP timeout), then stop; deliveries claimed
        but not sent become due again at once, for the next start or another gateway."""
        self._stopping = True
        self._wake.set()
        task, self._task = self._task, None
        if task is not None:
            # Attempts cut short are released below and due again: sent twice at worst.
            grace = min(self.settings.timeout_s + 1.0, STOP_GRACE_S)
            done, _ = await asyncio.wait({task}, timeout=grace)
            if not done:
                await cancel_and_wait(task)
        if self._claimed:
            try:
                await self._db(q.release, dict(self._claimed), time.time())
            except Exception as exc:  # their lease runs out instead
                log.warning("releasing claimed webhook deliveries failed: %s", exc)
            self._claimed.clear()
        if self._client is not None:
            await self._client.aclose()
            self._client = None

    def wake(self) -> None:
        """Look at the outbox now instead of at the next poll."""
        self._wake.set()

    @property
    def running(self) -> bool:
        return self._task is not None and not self._task.done()

    def status(self) -> dict[str, Any]:
        """For /readyz: whether it runs, its own last error, and the receivers' latest
        failed attempt (their problem, reported; deliveries wait in the outbox meanwhile)."""
        return {
            "running": self.running,
            "pending": self.pending,
            "last_error": self.last_error,
            "last_attempt_error": self.last_attempt_error,
            "failed": self.failed,
            "refusing": dict(self.refusing),
        }

    async def _db(
        self, fn: Callable[Concatenate[Connection, P], R], /, *args: P.args, **kwargs: P.kwargs
    ) -> R:
        return await run_in_transaction(self.engine, fn, *args, **kwargs)

    async def _run(self) -> None:
        s = self.settings
        backoff = Backoff(s.poll_s, max(s.poll_s, ROUND_RETRY_MAX_S))
        while not self._stopping:
            wait = s.poll_s
            try:
                more = await self.round()
                if backoff.failures:
                    log.info("webhook delivery: database reachable again")
                backoff.reset()
                self.last_error = None
            except Exception as exc:
                self.counters["errors"] += 1
                self.last_error = describe(exc)
                fault = classify(exc)
                if not fault.heals:  # a bug, or storage that will not heal: said once, ended
                    self.failed = f"{fault.reason}: {self.last_error}"
                    log.error(
                        "webhook delivery stopped, not retried: %s",
                        self.failed,
                        exc_info=exc if fault.bug else None,
                    )
                    return
                wait = backoff.next()  # the database may be away: try again after a backoff
                if backoff.failures == 1 or backoff.failures % 10 == 0:
                    log.warning(
                        "webhook delivery round failed (%d in a row), retrying in %.1f s: %s",
                        backoff.failures,
                        wait,
                        exc,
                    )
                more = False
            if not more and not self._stopping:
                with contextlib.suppress(TimeoutError):
                    async with asyncio.timeout(wait):
                        await self._wake.wait()
                self._wake.clear()

    async def round(self) -> bool:
        """Fan out new events, give up on expired deliveries, send the due ones. True when more
        work is waiting (a full batch)."""
        s = self.settings
        now = time.time()
        async with self._refresh_lock:
            fanned = await self._fan_out(now)
        for row in await self._db(q.give_up_expired, now=now, after_s=s.give_up_after_s):
            self.counters["failed"] += 1
            log.error(
                "webhook %s: gave up on event %s after %d attempts in %.0f s: %s",
                row["webhook_id"],
                row["event_id"],
                row["attempts"],
                s.give_up_after_s,
                row["last_error"],
            )
        claimed: list[dict[str, Any]] = await self._db(
            q.claim_due, now=now, lease_s=self.lease_s, limit=s.batch
        )
        self._claimed.update((r["id"], r["next_attempt_at"]) for r in claimed)
        if claimed:  # counted as the run starts, then at its steps
            await self._refresh(force=True)
        by_hook: dict[int, list[dict[str, Any]]] = {}
        for row in claimed:
            by_hook.setdefault(row["webhook_id"], []).append(row)
        if claimed and self._client is None:  # the first delivery of this run of the dispatcher
            self._client = await http_client(self.allow)
        await asyncio.gather(*(self._deliver(rows) for rows in by_hook.values()))
        await self._refresh(force=True)
        return fanned.events >= FAN_OUT_BATCH or len(claimed) >= s.batch

    async def _fan_out(self, now: float) -> q.FanOut:
        """One fan-out batch (the caller holds the refresh lock)."""
        s = self.settings
        fanned: q.FanOut = await self._db(
            q.fan_out, now=now, gaps=self._gaps, gap_wait_s=s.gap_wait_s, limit=FAN_OUT_BATCH
        )
        self.counters["queued"] += fanned.queued
        return fanned

    async def _refresh(self, *, force: bool = False) -> None:
        """Count the events not yet delivered per webhook; between the sends of a run (at most
        every STEP_REFRESH_S), fan out the events that came meanwhile first. A failure here
        leaves the counts as they were: sending goes on."""
        if not force and time.monotonic() - self._refreshed_at < STEP_REFRESH_S:
            return
        async with self._refresh_lock:
            self._refreshed_at = time.monotonic()
            try:
                if not force:
                    await self._fan_out(time.time())
                counts: dict[str, int] = await self._db(
                    q.undelivered_by_webhook, limit=FAN_OUT_BATCH
                )
            except Exception as exc:
                log.debug("counting undelivered webhook events failed: %s", exc)
                return
            self.pending_by_hook = counts
            self.pending = sum(counts.values())

    async def _hold(self, rest: list[dict[str, Any]], until: float) -> float | None:
        """The lease time under which the run's `rest` may be sent: `until` while one more
        attempt fits in it with the margin, else renewed; None when it cannot be (the database
        is away, or another gateway took the run after its lease ran out): stop sending."""
        s = self.settings
        need = s.timeout_s + s.lease_margin_s
        if until - time.time() >= need:
            return until
        ids = [r["id"] for r in rest]
        new_until = time.time() + self.lease_s
        try:
            kept = await self._db(q.renew_claim, ids, until=until, new_until=new_until)
        except Exception as exc:
            self.last_error = describe(exc)
            log.warning(
                "webhook %s: cannot renew the claim of %d deliveries, sending stops until "
                "it runs out: %s",
                rest[0]["webhook_name"],
                len(ids),
                exc,
            )
            return None
        if not kept:
            self.counters["claims_lost"] += 1
            for delivery_id in ids:
                self._claimed.pop(delivery_id, None)
            log.warning(
                "webhook %s: the claim of %d deliveries ran out and another gateway holds "
                "them; this one stops sending them",
                rest[0]["webhook_name"],
                len(ids),
            )
            return None
        self.counters["claims_renewed"] += 1
        for delivery_id in ids:
            self._claimed[delivery_id] = new_until
        if new_until - time.time() < need:  # the renewal itself took too long
            return await self._hold(rest, new_until)
        return new_until

    async def _attempt(self, row: dict[str, Any], now: float) -> Attempt:
        """One attempt (a POST, or an email), bounded in all by timeout_s (httpx bounds each
        phase, not the sum)."""
        if row["payload"] is None:
            return Attempt(False, None, "the alert event is no longer stored", 0.0)
        assert self._client is not None
        timeout = self.settings.timeout_s
        body = event_body(row["payload"], row["event_id"], self.public_url)
        try:
            async with asyncio.timeout(timeout):
                return await send(
                    self._client,
                    row,
                    body,
                    delivery_id=row["id"],
                    now=now,
                    timeout=timeout,
                    smtp=self.smtp,
                )
        except TimeoutError:
            return Attempt(False, None, f"no complete answer within {timeout:g} s", timeout)

    async def _deliver(self, rows: list[dict[str, Any]]) -> None:
        """One webhook's claimed deliveries in event order; the first failure postpones the
        rest to its own retry time (a receiver that is down gets one attempt per backoff).
        Before each attempt the claim is renewed if the attempt could outlast it; a run whose
        claim cannot be kept is not sent further."""
        s = self.settings
        until: float | None = rows[0]["next_attempt_at"] if rows else None
        for i, row in enumerate(rows):
            if self._stopping or until is None:
                return
            until = await self._hold(rows[i:], until)
            if until is None or self._stopping:
                return
            attempt = await self._attempt(row, time.time())
            now = time.time()
            if attempt.delivered:
                await self._db(
                    q.record_attempt,
                    row["id"],
                    now=now,
                    delivered=True,
                    status=attempt.status,
                    error=None,
                )
                self._claimed.pop(row["id"], None)
                self.counters["delivered"] += 1
                if self.refusing.pop(row["webhook_name"], None) is not None:
                    log.info("webhook %s accepts deliveries again", row["webhook_name"])
                await self._refresh()
                continue
            attempts = row["attempts"] + 1
            give_up = row["payload"] is None or now - row["created_at"] >= s.give_up_after_s
            retry_at = now + backoff_delay(attempts, s.retry_initial_s, s.retry_max_s)
            if attempt.status is not None and not http_status_heals(attempt.status):
                # The receiver refuses (a wrong secret, a gone address): the next try would
                # hear the same until someone fixes it there. Said once, reported, tried at
                # the longest delay only; the events wait (at least once) until given up.
                retry_at = now + s.retry_max_s
                self.counters["refused"] += 1
                if row["webhook_name"] not in self.refusing:
                    log.error(
                        "webhook %s (%s) refuses deliveries: %s; no retry cures that, its "
                        "events are tried every %.0f s until fixed or given up after %.0f s",
                        row["webhook_name"],
                        redact_url(row["url"], row["format"]),
                        attempt.error,
                        s.retry_max_s,
                        s.give_up_after_s,
                    )
                self.refusing[row["webhook_name"]] = attempt.error or f"HTTP {attempt.status}"
            await self._db(
                q.record_attempt,
                row["id"],
                now=now,
                delivered=False,
                status=attempt.status,
                error=attempt.error,
                next_attempt_at=retry_at,
                give_up=give_up,
            )
            self._claimed.pop(row["id"], None)
            self.last_attempt_error = {
                "webhook": row["webhook_name"],
                "status": attempt.status,
                "error": attempt.error,
                "at": now,
            }
            if give_up:
                self.counters["failed"] += 1
                log.error(
                    "webhook %s (%s): gave up on event %s after %d attempts: %s",
                    row["webhook_name"],
                    redact_url(row["url"], row["format"]),
                    row["event_id"],
                    attempts,
                    attempt.error,
                )
                continue
            self.counters["retried"] += 1
            if row["webhook_name"] in self.refusing:
                pass  # said when it started refusing
            elif attempts == 1 or attempts % 10 == 0:
                log.warning(
                    "webhook %s (%s): event %s attempt %d failed, retrying in %.1f s: %s",
                    row["webhook_name"],
                    redact_url(row["url"], row["format"]),
                    row["event_id"],
                    attempts,
                    retry_at - now,
                    attempt.error,
                )
            rest = [r["id"] for r in rows[i + 1 :]]
            await self._db(q.postpone, rest, retry_at)
            for delivery_id in rest:
                self._claimed.pop(delivery_id, None)
            return

    async def send_test(self, hook: dict[str, Any]) -> dict[str, Any]:
        """POST a signed test event to a webhook now and log it; the outcome is returned."""
        client = self._client or await http_client(self.allow)
        try:
            return await send_test(
                client, self.engine, hook, self.public_url, self.settings, self.smtp
            )
        finally:
            if client is not self._client:
                await client.aclose()


async def http_client(allow: tuple[IPNetwork, ...]) -> httpx.AsyncClient:
    """A webhook client (eqgw.notify.guarded). The first one of a process loads the HTTP
    stack, in a thread so that the event loop goes on meanwhile: a gateway loads it when it
    first sends a webhook, not at its start."""
    if "eqgw.notify.guarded" not in sys.modules:
        await asyncio.to_thread(importlib.import_module, "eqgw.notify.guarded")
    from eqgw.notify.guarded import guarded_client

    return guarded_client(allow)


async def send_test(
    client: httpx.AsyncClient,
    engine: Engine,
    hook: dict[str, Any],
    public_url: str,
    settings: DeliverySettings,
    smtp: SmtpSettings | None = None,
) -> dict[str, Any]:
    """POST a signed test event (`event` "test", id `test-...`) once, log it, report it."""
    now = time.time()
    event_id = f"test-{uuid.uuid4().hex[:16]}"
    body = event_body(test_payload(now), event_id, public_url)
    # Logged before it is sent, so the POST carries its delivery id like every other delivery;
    # a row left "failed" with no attempt is a test the process did not live to send.
    row = {
        "webhook_id": hook["id"],
        "event_id": None,
        "kind": "test",
        "alert_id": None,
        "state": "failed",
        "attempts": 0,
        "created_at": now,
        "next_attempt_at": now,
        "last_attempt_at": None,
        "last_status": None,
        "last_error": "not sent",
        "delivered_at": None,
    }

    def store() -> int:
        with engine.begin() as conn:
            return q.add_test_delivery(conn, row)

    delivery_id = await asyncio.to_thread(store)
    attempt = await send(
        client,
        hook,
        body,
        delivery_id=delivery_id,
        now=now,
        timeout=settings.timeout_s,
        smtp=smtp,
    )
    done = time.time()
    outcome = {
        "state": "delivered" if attempt.delivered else "failed",
        "attempts": 1,
        "next_attempt_at": done,
        "last_attempt_at": done,
        "last_status": attempt.status,
        "last_error": attempt.error[:2000] if attempt.error else None,
        "delivered_at": done if attempt.delivered else None,
    }

    def finish() -> None:
        with engine.begin() as conn:
            q.finish_test_delivery(conn, delivery_id, outcome)

    await asyncio.to_thread(finish)
    return {
        "delivered": attempt.delivered,
        "status": attempt.status,
        "error": attempt.error,
        "duration_ms": round(attempt.duration_s * 1000, 1),
        "event_id": event_id,
        "delivery_id": delivery_id,
    }


class DeliveryCollector(Collector):
    """Delivery counters for Prometheus, read at scrape time."""

    def __init__(self, delivery: AlertDelivery) -> None:
        self.delivery = delivery

    def collect(self) -> Iterator[Metric]:
        hooks = self.delivery.webhooks
        counts = hooks.counters if hooks else Counter()
        outcomes = CounterMetricFamily(
            "eqgw_webhook_attempts",
            "Webhook delivery attempts by outcome (retried: failed, tried again later; "
            "failed: given up after the retry period)",
            labels=["outcome"],
        )
        for outcome in ("delivered", "retried", "failed"):
            outcomes.add_metric([outcome], counts[outcome])
        yield outcomes
        yield CounterMetricFamily(
            "eqgw_webhook_queued", "Deliveries queued (event x webhook)", value=counts["queued"]
        )
        pending = GaugeMetricFamily(
            "eqgw_webhook_pending",
            "Alert events not yet delivered nor failed, per webhook (queued deliveries and "
            "matching events not yet queued), counted at every delivery step",
            labels=["webhook"],
        )
        for name, n in sorted((hooks.pending_by_hook if hooks else {}).items()):
            pending.add_metric([name], n)
        yield pending
        refusing = GaugeMetricFamily(
            "eqgw_webhook_refusing",
            "1 for a webhook whose receiver refuses deliveries for a reason no retry cures "
            "(HTTP 4xx but 408/425/429); its events wait, tried at the longest delay",
            labels=["webhook"],
        )
        for name in sorted(hooks.refusing if hooks else ()):
            refusing.add_metric([name], 1.0)
        yield refusing
        mqtt = self.delivery.mqtt
        failed = GaugeMetricFamily(
            "eqgw_alert_delivery_failed",
            "1 for an alert delivery loop stopped for good (a bug, storage or credentials "
            "that will not heal; the reason in /readyz)",
            labels=["loop"],
        )
        failed.add_metric(["webhooks"], 1.0 if hooks is not None and hooks.failed else 0.0)
        failed.add_metric(["mqtt"], 1.0 if mqtt is not None and mqtt.failed else 0.0)
        yield failed
        yield CounterMetricFamily(
            "eqgw_webhook_round_failures",
            "Delivery rounds that failed on our side (the database), retried at the next poll",
            value=counts["errors"],
        )
        mqtt = self.delivery.mqtt
        if mqtt is not None:
            yield CounterMetricFamily(
                "eqgw_mqtt_published",
                "Alert events acknowledged by the MQTT broker",
                value=mqtt.counters["published"],
            )
            yield CounterMetricFamily(
                "eqgw_mqtt_publish_failures",
                "MQTT publish rounds that failed or timed out",
                value=mqtt.counters["failures"],
            )
            yield GaugeMetricFamily(
                "eqgw_mqtt_connected",
                "1 while connected to the broker",
                value=1.0 if mqtt.connected else 0.0,
            )


class AlertDelivery:
    """Everything that delivers alert events from one gateway: webhooks, and MQTT when a
    broker is configured. Started and stopped by the app's lifespan."""

    def __init__(self, engine: Engine, settings: Settings, public_url: str) -> None:
        from eqgw.notify.mqtt import MqttPublisher

        self.engine = engine
        self.settings = settings
        self.public_url = public_url
        self.webhooks = (
            WebhookDispatcher(
                engine,
                settings.delivery,
                public_url,
                parse_networks(settings.webhook_allow_networks),
                settings.smtp,
            )
            if settings.delivery.enabled
            else None
        )
        self.mqtt = (
            MqttPublisher(engine, settings.mqtt, settings.delivery, public_url)
            if settings.delivery.enabled and settings.mqtt.host
            else None
        )
        self.collector = DeliveryCollector(self)
        self._registry: CollectorRegistry | None = None

    async def prepare(self) -> None:
        """Before the alert engine starts: MQTT's cursor exists, so that every event raised
        from then on is published (its first start creates it, see `MqttPublisher`)."""
        if self.mqtt is not None:
            await asyncio.to_thread(self.mqtt.ensure_cursor)

    async def start(self, registry: CollectorRegistry | None = None) -> None:
        if self.webhooks is not None:
            await self.webhooks.start()
        if self.mqtt is not None:
            await self.mqtt.start()
        if registry is not None:
            registry.register(self.collector)
            self._registry = registry

    async def stop(self) -> None:
        if self._registry is not None:
            self._registry.unregister(self.collector)
            self._registry = None
        if self.mqtt is not None:
            await self.mqtt.stop()
        if self.webhooks is not None:
            await self.webhooks.stop()

    def status(self) -> dict[str, Any]:
        """For /readyz: the webhook dispatcher's and MQTT publisher's state."""
        out: dict[str, Any] = {
            "webhooks": self.webhooks.status() if self.webhooks is not None else None
        }
        if self.mqtt is not None:
            out["mqtt"] = {
                "connected": self.mqtt.connected,
                "last_error": self.mqtt.last_error,
                "failed": self.mqtt.failed,
            }
        return out

    def wake(self) -> None:
        """New alert events were written: deliver now rather than at the next poll."""
        if self.webhooks is not None:
            self.webhooks.wake()
        if self.mqtt is not None:
            self.mqtt.wake()

    async def send_test(self, hook: dict[str, Any]) -> dict[str, Any]:
        """The "send test" action (works with delivery disabled too)."""
        if self.webhooks is not None:
            return await self.webhooks.send_test(hook)
        allow = parse_networks(self.settings.webhook_allow_networks)
        async with await http_client(allow) as client:
            return await send_test(
                client, self.engine, hook, self.public_url, self.settings.delivery
            )
