"""Webhook delivery: signatures, retries against a real receiver that fails or is down, a
restart in between, each event received once; filters, give-up, claims across gateways."""

from __future__ import annotations

import asyncio
import json
import random
import re
import time
from collections import Counter
from typing import Any

from sqlalchemy import Engine, update

from eqgw.config import DeliverySettings, Settings
from eqgw.notify import repository as q
from eqgw.notify.delivery import AlertDelivery
from eqgw.notify.senders import email_message
from eqgw.notify.webhooks import (
    LEGACY_SIGNATURE_HEADER,
    SIGNATURE_HEADER,
    TIMESTAMP_HEADER,
    event_body,
    render,
    signature,
    slack_body,
    verify,
)
from eqgw.store.webhook_models import WebhookDelivery
from eqgw.tasks import Backoff, backoff_delay
from tests.api_helpers import wait_for
from tests.webhook_helpers import (
    ALLOW_LOOPBACK,
    SECRET,
    Receiver,
    add_alert,
    add_event,
    deliveries,
    make_hook,
)

PUBLIC = "http://eqgw.example:8000"


def fast(**kw: Any) -> DeliverySettings:
    """Small delays so retries happen within a test (never timing assertions on them)."""
    base: dict[str, Any] = {
        "poll_s": 0.05,
        "timeout_s": 5.0,
        "retry_initial_s": 0.1,
        "retry_max_s": 0.4,
        "gap_wait_s": 0.5,
    }
    return DeliverySettings(**{**base, **kw})


def delivery(engine: Engine, settings: DeliverySettings) -> AlertDelivery:
    config = Settings(
        database_url="sqlite://", delivery=settings, webhook_allow_networks=ALLOW_LOOPBACK
    )
    return AlertDelivery(engine, config, PUBLIC)


# -- pure parts ---------------------------------------------------------------------------


def test_signature_is_standard_webhooks_hmac_over_id_timestamp_and_body() -> None:
    body = {"event": "raised", "event_id": 7, "alert": {"id": 3, "vehicle_id": "BUS-1"}}
    content, headers = render("json", body, SECRET, delivery_id=11, now=1_700_000_000.5)
    assert headers["webhook-id"] == "7" and headers[TIMESTAMP_HEADER] == "1700000000"
    assert headers["X-Eqgw-Event-Id"] == "7" and headers["X-Eqgw-Delivery"] == "11"
    import base64
    import hashlib
    import hmac

    # A secret without the whsec_ prefix is a "raw" key: its UTF-8 bytes.
    mac = hmac.new(SECRET.encode(), b"7.1700000000." + content, hashlib.sha256).digest()
    assert headers[SIGNATURE_HEADER] == "v1," + base64.b64encode(mac).decode()
    legacy = hmac.new(SECRET.encode(), b"1700000000." + content, hashlib.sha256).hexdigest()
    assert headers[LEGACY_SIGNATURE_HEADER] == f"sha256={legacy}"
    assert json.loads(content) == body
    assert verify(SECRET, headers, content, now=1_700_000_100)
    assert not verify(SECRET, headers, content + b" ", now=1_700_000_100)
    assert not verify("other-secret-other", headers, content, now=1_700_000_100)
    assert not verify(SECRET, headers, content, now=1_700_000_000 + 301)  # replayed too late
    assert not verify(SECRET, {**headers, "webhook-id": "8"}, content, now=1_700_000_100)
    assert signature(SECRET, "1", "1", b"x") != signature(SECRET, "1", "2", b"x")


def test_body_links_and_slack_format() -> None:
    alert = {"id": 5, "vehicle_id": "BUS-9", "vehicle_name": "Bus 9", "rule": "imbalance",
             "severity": "critical", "message": "B - A 0.62 V", "values": {"b_minus_a_v": 0.62},
             "bus": "BUS-9/can0", "sa": 30}  # fmt: skip
    body = event_body({"event": "raised", "ts": 1.0, "alert": alert}, 42, PUBLIC + "/")
    assert body["event_id"] == 42
    assert body["links"] == {
        "vehicle": "http://eqgw.example:8000/#/vehicle/BUS-9",
        "alert": "http://eqgw.example:8000/api/v1/alerts/5",
    }
    slack = slack_body(body)
    assert "CRITICAL imbalance raised on Bus 9" in slack["text"]
    assert slack["blocks"][0]["type"] == "section"
    assert "http://eqgw.example:8000/#/vehicle/BUS-9" in json.dumps(slack["blocks"])
    content, headers = render("slack", body, SECRET, delivery_id=1, now=time.time())
    assert set(json.loads(content)) == {"text", "blocks"} and verify(SECRET, headers, content)


def test_backoff_doubles_to_the_cap_with_jitter() -> None:
    lows = [backoff_delay(n, 5.0, 600.0, rand=lambda: 0.0) for n in range(1, 10)]
    highs = [backoff_delay(n, 5.0, 600.0, rand=lambda: 1.0) for n in range(1, 10)]
    assert highs[:5] == [5.0, 10.0, 20.0, 40.0, 80.0]
    assert highs[-1] == 600.0 and lows[-1] == 300.0
    assert all(lo == hi / 2 for lo, hi in zip(lows, highs, strict=True))
    assert backoff_delay(10_000, 5.0, 600.0) <= 600.0


def test_retries_and_emails_leave_the_random_modules_state_alone() -> None:
    """The jitter and an email's Message-ID draw from generators of their own: a gateway run
    inside a program (a test run drawing with Hypothesis, which checks that state around
    each draw, or a simulation that seeded `random`) retrying or mailing in a background
    thread does not change what that program draws next."""
    state = random.getstate()
    delays = [backoff_delay(n, 5.0, 600.0) for n in range(1, 20)]
    backoff = Backoff(1.0, 30.0)
    delays += [backoff.next() for _ in range(20)]
    mails = [email_message({"event_id": n}, "eqgw@depot", ["ops@depot"]) for n in range(5)]
    ids = {mail["Message-ID"] for mail in mails}
    assert random.getstate() == state
    assert len(set(delays)) > 30  # still jittered
    assert len(ids) == 5 and all(re.fullmatch(r"<\d+\.\d+\.\d+@eqgw>", i) for i in ids), ids


def test_readable_count_waits_for_a_gap_then_passes_it() -> None:
    gaps: dict[int, float] = {}
    assert q.readable_count(0, [1, 2, 4, 5], gaps, now=100.0, wait_s=5.0) == 2
    assert q.readable_count(2, [4, 5], gaps, now=102.0, wait_s=5.0) == 0
    assert q.readable_count(2, [3, 4, 5], gaps, now=103.0, wait_s=5.0) == 3  # it committed
    assert q.readable_count(5, [7], gaps, now=200.0, wait_s=5.0) == 0
    assert q.readable_count(5, [7], gaps, now=206.0, wait_s=5.0) == 1  # rolled back: passed
    assert gaps == {}


# -- against a real receiver --------------------------------------------------------------


async def test_retries_restart_and_each_event_once(engine: Engine) -> None:
    receiver = Receiver(SECRET, status=500).start()
    hook = make_hook(engine, receiver.url)
    alert = add_alert(engine)
    first = [add_event(engine, alert, "raised"), add_event(engine, alert, "acknowledged")]
    muted = add_event(engine, add_alert(engine, rule="offline"), "raised", muted=True)
    gw = delivery(engine, fast())
    await gw.start()
    try:
        # The receiver answers 500: the oldest event is retried, the next waits behind it.
        await wait_for(
            lambda: _async(receiver.attempts_for(first[0]) >= 3), what="retries after 500s"
        )
        assert receiver.accepted() == []
        rows = deliveries(engine, hook)
        assert {r["state"] for r in rows} == {"pending"}
        assert max(r["attempts"] for r in rows) >= 2  # the third may still be recording
        assert any(r["last_status"] == 500 for r in rows)
    finally:
        await gw.stop()
    # eqgw is down, then the receiver too; events keep coming.
    receiver.stop()
    later = [add_event(engine, alert, "cleared"), add_event(engine, add_alert(engine), "raised")]
    gw = delivery(engine, fast())
    await gw.start()
    try:

        async def refused() -> bool:
            rows = deliveries(engine, hook)
            return any(
                r["last_status"] is None and r["last_error"] and r["attempts"] > 3 for r in rows
            )

        await wait_for(refused, what="attempts against the receiver that is down")
        receiver.status = 200
        receiver.start()  # same port: it is back

        async def all_in() -> bool:
            return len(receiver.accepted()) >= 4

        await wait_for(all_in, what="every event delivered after recovery")
        await asyncio.sleep(0.5)  # a duplicate would show up in this time
    finally:
        await gw.stop()
        receiver.stop()
    got = [b["event_id"] for b in receiver.accepted()]
    assert Counter(got) == Counter(first + later)  # each once; the muted one never
    assert muted not in got
    assert got == sorted(got)  # one webhook: in event order
    assert receiver.bad_signatures == 0
    body = receiver.accepted()[0]
    assert body["event"] == "raised" and body["alert"]["id"] == alert["id"]
    assert body["links"]["vehicle"] == f"{PUBLIC}/#/vehicle/BUS-1"
    rows = deliveries(engine, hook)
    assert len(rows) == 4 and {r["state"] for r in rows} == {"delivered"}
    assert all(r["last_status"] == 200 and r["delivered_at"] for r in rows)
    assert gw.webhooks is not None and gw.webhooks.counters["retried"] > 0


async def test_gives_up_after_the_retry_period(engine: Engine) -> None:
    receiver = Receiver(SECRET, status=503).start()
    hook = make_hook(engine, receiver.url)
    event = add_event(engine, add_alert(engine), "raised")
    gw = delivery(engine, fast(give_up_after_s=0.6))
    await gw.start()
    try:

        async def failed() -> bool:
            rows = deliveries(engine, hook)
            return bool(rows) and rows[0]["state"] == "failed"

        await wait_for(failed, what="the delivery given up")
    finally:
        await gw.stop()
        receiver.stop()
    row = deliveries(engine, hook)[0]
    assert row["event_id"] == event and row["attempts"] >= 1 and "503" in row["last_error"]
    assert gw.webhooks is not None and gw.webhooks.counters["failed"] == 1


async def test_a_run_longer_than_its_lease_keeps_its_claim(engine: Engine) -> None:
    """Ten events at 0.3 s each outlast a 3 s lease: the claim is renewed on the way (on
    either database), and every event is sent once."""
    receiver = Receiver(SECRET, delay_s=0.3).start()
    make_hook(engine, receiver.url)
    ids = [add_event(engine, add_alert(engine), "raised") for _ in range(10)]
    gw = delivery(engine, fast(timeout_s=1.0, lease_s=3.0))
    await gw.start()
    try:
        await wait_for(lambda: _async(len(receiver.accepted()) >= len(ids)), what="the run")
    finally:
        await gw.stop()
        receiver.stop()
    assert [b["event_id"] for b in receiver.accepted()] == ids
    assert gw.webhooks is not None
    assert gw.webhooks.counters["claims_renewed"] >= 1
    assert gw.webhooks.counters["claims_lost"] == 0


async def test_a_run_whose_claim_was_taken_is_not_sent_further(engine: Engine) -> None:
    """Another gateway claimed the rest of a run after its lease (as one would once the lease
    ran out): the sender finds out when it renews and sends none of it."""
    receiver = Receiver(SECRET, delay_s=0.3).start()
    hook = make_hook(engine, receiver.url)
    ids = [add_event(engine, add_alert(engine), "raised") for _ in range(10)]
    gw = delivery(engine, fast(timeout_s=1.0, lease_s=3.0))
    await gw.start()
    try:
        await wait_for(lambda: _async(len(receiver.requests) >= 1), what="the run under way")
        taken = time.time() + 3600.0  # the other gateway's lease
        with engine.begin() as conn:
            conn.execute(
                update(WebhookDelivery)
                .where(WebhookDelivery.state == "pending")
                .values(next_attempt_at=taken)
            )
        assert gw.webhooks is not None
        hooks = gw.webhooks
        await wait_for(lambda: _async(hooks.counters["claims_lost"] >= 1), what="claim lost")
        sent = len(receiver.requests)
        await asyncio.sleep(0.5)
    finally:
        await gw.stop()
        receiver.stop()
    # Sent until its next renewal at most (its lease still ran then): the rest is the other's.
    assert sent < len(ids) and len(receiver.requests) == sent
    rows = deliveries(engine, hook)
    left = [r for r in rows if r["state"] == "pending"]
    assert len(left) == len(ids) - sent
    assert all(r["next_attempt_at"] == taken for r in left)  # not released by the stop


async def test_filters_disabled_hooks_and_rule_targets(engine: Engine) -> None:
    receiver = Receiver(SECRET).start()
    crit = make_hook(engine, receiver.url, name="critical-only", min_severity="critical")
    cleared = make_hook(engine, receiver.url, name="cleared-only", kinds=["cleared"])
    bus2 = make_hook(engine, receiver.url, name="bus2", vehicles=["BUS-2"])
    off = make_hook(engine, receiver.url, name="off", enabled=False)
    warn = add_alert(engine, severity="warning")
    crit_alert = add_alert(engine, vehicle_id="BUS-2", rule="overvoltage", severity="critical")
    e1 = add_event(engine, warn, "raised")
    e2 = add_event(engine, crit_alert, "raised")
    e3 = add_event(engine, warn, "cleared")
    gw = delivery(engine, fast())
    await gw.start()
    try:

        async def done() -> bool:
            return len(receiver.accepted()) >= 3

        await wait_for(done, what="filtered deliveries")
        await asyncio.sleep(0.3)
    finally:
        await gw.stop()
        receiver.stop()
    assert [r["event_id"] for r in deliveries(engine, crit)] == [e2]
    assert [r["event_id"] for r in deliveries(engine, cleared)] == [e3]
    assert [r["event_id"] for r in deliveries(engine, bus2)] == [e2]
    assert deliveries(engine, off) == []
    assert e1 not in [b["event_id"] for b in receiver.accepted()]


def test_fan_out_is_once_per_event_and_claims_skip_locked_rows(engine: Engine) -> None:
    hook = make_hook(engine, "http://127.0.0.1:9/")
    alert = add_alert(engine)
    ids = [add_event(engine, alert, "raised") for _ in range(4)]
    gaps: dict[int, float] = {}
    with engine.begin() as conn:
        assert q.fan_out(conn, now=time.time(), gaps=gaps, gap_wait_s=0, limit=100).queued == 4
    with engine.begin() as conn:
        assert q.fan_out(conn, now=time.time(), gaps=gaps, gap_wait_s=0, limit=100).queued == 0
    assert sorted(r["event_id"] for r in deliveries(engine, hook)) == ids
    now = time.time()
    if engine.dialect.name != "postgresql":
        with engine.begin() as conn:
            assert [r["event_id"] for r in q.claim_due(conn, now=now, lease_s=60, limit=2)] == (
                ids[:2]
            )
        with engine.begin() as conn:  # the oldest is leased: nothing may overtake it
            assert q.claim_due(conn, now=now, lease_s=60, limit=10) == []
        return
    # Two gateways claiming at the same moment: one takes the webhook's oldest run, the other
    # skips that webhook (it would otherwise send later events beside the first's).
    with engine.connect() as a, engine.connect() as b:
        ta, tb = a.begin(), b.begin()
        got_a = q.claim_due(a, now=now, lease_s=60, limit=2)
        got_b = q.claim_due(b, now=now, lease_s=60, limit=10)
        ta.commit()
        tb.commit()
    assert [r["event_id"] for r in got_a] == ids[:2] and got_b == []
    with engine.begin() as conn:  # and later too, while the run is leased
        assert q.claim_due(conn, now=now, lease_s=60, limit=10) == []


async def test_events_arrive_in_order_after_an_outage_with_two_gateways(db_url: str) -> None:
    """A receiver down while 36 alerts are raised and cleared, two gateways delivering in
    small batches: once it is back, every event arrives once and strictly in event order."""
    from eqgw.store.engine import create_engine
    from eqgw.store.migrate import upgrade_engine

    engines = [create_engine(db_url) for _ in range(2)]
    upgrade_engine(engines[0])
    receiver = Receiver(SECRET, status=503).start()
    hook = make_hook(engines[0], receiver.url)
    gateways = [delivery(e, fast(batch=4, retry_initial_s=0.05, retry_max_s=0.3)) for e in engines]
    for gw in gateways:
        await gw.start()
    ids: list[int] = []
    try:
        for n in range(36):
            alert = add_alert(engines[0], vehicle_id=f"BUS-{n}")
            ids.append(add_event(engines[0], alert, "raised"))
            ids.append(add_event(engines[0], alert, "cleared"))
            await asyncio.sleep(0.01)

        async def queued() -> bool:
            rows = deliveries(engines[0], hook)
            return len(rows) == len(ids) and sum(r["attempts"] for r in rows) >= 5

        await wait_for(queued, what="every event queued and the first ones failing")
        receiver.status = 200

        async def all_in() -> bool:
            return len(receiver.accepted()) >= len(ids)

        await wait_for(all_in, what="every event delivered after the outage")
        await asyncio.sleep(0.3)  # a duplicate would show up in this time
    finally:
        for gw in gateways:
            await gw.stop()
        receiver.stop()
        for e in engines:
            e.dispose()
    got = [b["event_id"] for b in receiver.accepted()]
    assert got == ids


async def _async(value: Any) -> Any:
    return value
