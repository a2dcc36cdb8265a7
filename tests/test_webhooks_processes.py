"""Two `eqgw serve` processes on one PostgreSQL deliver a webhook's events once each and in
event order, also after the receiver was down while the events piled up and both processes
were retrying them."""

from __future__ import annotations

import re
import time
from pathlib import Path

import httpx
import pytest

from eqgw.store.engine import create_engine
from eqgw.store.migrate import upgrade_engine
from tests.cluster_helpers import METRICS_TOKEN, readyz, start_gateway
from tests.proc_helpers import wait_until
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
    r = httpx.get(f"{base}/metrics", headers={"Authorization": f"Bearer {METRICS_TOKEN}"})
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
