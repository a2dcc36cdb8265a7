"""Two `eqgw serve` processes on one PostgreSQL deliver a webhook's events once each and in
event order, also after the receiver was down while the events piled up and both processes
were retrying them."""

from __future__ import annotations

import re
import time
from pathlib import Path

import pytest

from eqgw.store.engine import create_engine
from eqgw.store.migrate import upgrade_engine
from tests.cluster_helpers import METRICS_TOKEN, readyz, start_gateway
from tests.proc_helpers import wait_until
from tests.support import web
from tests.webhook_helpers import (
    ALLOW_LOOPBACK,
    SECRET,
    Receiver,
    add_alert,
    add_event,
    deliveries,
    make_hook,
)

pytestmark = pytest.mark.postgres

# Small batches and quick retries, so that both processes claim, fail and retry many times.
DELIVERY = """
[delivery]
poll_s = 0.05
batch = 4
retry_initial_s = 0.05
retry_max_s = 0.3
gap_wait_s = 0.5
"""
ATTEMPTS = re.compile(r'^eqgw_webhook_attempts_total\{outcome="(\w+)"\} (\S+)$', re.M)


def _attempts(base: str) -> dict[str, float]:
    r = web.get(f"{base}/metrics", headers={"Authorization": f"Bearer {METRICS_TOKEN}"})
    return {outcome: float(n) for outcome, n in ATTEMPTS.findall(r.text)}


def test_two_gateway_processes_deliver_every_event_once_in_order(
    pg_url: str, tmp_path: Path
) -> None:
    engine = create_engine(pg_url)
    upgrade_engine(engine)
    receiver = Receiver(SECRET, status=503).start()
    fleet = tmp_path / "fleet.toml"
    fleet.write_text(DELIVERY)
    env = {"EQGW_WEBHOOK_ALLOW_NETWORKS": ALLOW_LOOPBACK}
    gateways = [start_gateway(tmp_path, pg_url, fleet, f"wh-{n}", extra_env=env) for n in range(2)]
    try:
        for _, base in gateways:
            wait_until(lambda b=base: (readyz(b) or {}).get("ready"), 60, f"{base} ready")
        hook = make_hook(engine, receiver.url)
        ids: list[int] = []
        for n in range(36):
            alert = add_alert(engine, vehicle_id=f"BUS-{n}")
            ids.append(add_event(engine, alert, "raised"))
            ids.append(add_event(engine, alert, "cleared"))
            time.sleep(0.01)

        def retried_by_both() -> bool:
            rows = deliveries(engine, hook)
            return len(rows) == len(ids) and all(
                _attempts(base).get("retried", 0) >= 2 for _, base in gateways
            )

        wait_until(retried_by_both, 60, "every event queued and both processes retrying")
        receiver.status = 200
        wait_until(lambda: len(receiver.accepted()) >= len(ids), 60, "every event delivered")
        time.sleep(0.5)  # a duplicate would show up in this time
        delivered = [_attempts(base).get("delivered", 0) for _, base in gateways]
    finally:
        for proc, _ in gateways:
            proc.stop()
        receiver.stop()
        engine.dispose()
    got = [b["event_id"] for b in receiver.accepted()]
    assert got == ids
    assert sum(delivered) == len(ids), delivered


# A receiver slower than the claim lease is long: a run of deliveries outlasts its first lease.
SLOW = """
[delivery]
poll_s = 0.05
timeout_s = 1.0
lease_s = 3.0
"""
PENDING = re.compile(r'^eqgw_webhook_pending\{webhook="slow"\} (\S+)$', re.M)


def _pending(base: str) -> float | None:
    r = web.get(f"{base}/metrics", headers={"Authorization": f"Bearer {METRICS_TOKEN}"})
    m = PENDING.search(r.text)
    return float(m.group(1)) if m else None


def test_a_run_longer_than_its_lease_is_sent_by_one_gateway_and_counted_as_it_goes(
    pg_url: str, tmp_path: Path
) -> None:
    """Two live gateways, a receiver answering in 0.5 s and a 3 s claim lease: the gateway
    sending a run of 10 events (5 s) keeps its claim, so the other sends none of them; both
    report the events not yet delivered while the run goes on."""
    engine = create_engine(pg_url)
    upgrade_engine(engine)
    receiver = Receiver(SECRET, delay_s=0.5).start()
    fleet = tmp_path / "fleet.toml"
    fleet.write_text(SLOW)
    env = {"EQGW_WEBHOOK_ALLOW_NETWORKS": ALLOW_LOOPBACK}
    gateways = [
        start_gateway(tmp_path, pg_url, fleet, f"slow-{n}", extra_env=env) for n in range(2)
    ]
    seen: list[list[float]] = [[], []]
    try:
        for _, base in gateways:
            wait_until(lambda b=base: (readyz(b) or {}).get("ready"), 60, f"{base} ready")
        make_hook(engine, receiver.url, name="slow")
        ids = [
            add_event(engine, add_alert(engine, vehicle_id=f"BUS-{n}"), "raised") for n in range(10)
        ]

        def all_sent() -> bool:
            for i, (_, base) in enumerate(gateways):
                n = _pending(base)
                if n is not None:
                    seen[i].append(n)
            return len(receiver.requests) >= len(ids)

        wait_until(all_sent, 60, "every event sent", interval=0.2)
        # A second gateway taking over the run would send its rest again within a lease.
        deadline = time.monotonic() + 1.0
        while time.monotonic() < deadline and len(receiver.requests) == len(ids):
            time.sleep(0.2)
        sent = [r.json["event_id"] for r in receiver.requests]
        assert sent == ids, f"sent {len(sent)} for {len(ids)} events: {sent}"
        wait_until(lambda: all(_pending(base) == 0 for _, base in gateways), 30, "nothing pending")
    finally:
        for proc, _ in gateways:
            proc.stop()
        receiver.stop()
        engine.dispose()
    # Each gateway counted the undelivered events while the run went on, not only after it.
    for samples in seen:
        assert any(1 <= n <= len(ids) for n in samples), samples
        assert max(samples) <= len(ids), samples
