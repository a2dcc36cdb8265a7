"""A real `eqgw serve` publishes to the local Mosquitto (127.0.0.1:1883) every event of an
alert raised before its publisher ever started, and the events raised while it was stopped:
the MQTT cursor is persisted, created past the history (alerts already cleared) but before
every event of the alerts still open, and before the alert engine starts."""

from __future__ import annotations

import uuid
from pathlib import Path

from sqlalchemy import Engine

from tests.cluster_helpers import readyz, start_gateway
from tests.proc_helpers import Process, wait_until
from tests.test_webhooks_mqtt import Subscriber, pytestmark  # noqa: F401 (skip: no broker)
from tests.webhook_helpers import add_alert, add_event


def _gateway(tmp_path: Path, db_url: str, prefix: str, n: int) -> Process:
    fleet = tmp_path / "fleet.toml"
    fleet.write_text("[delivery]\npoll_s = 0.1\n")
    env = {"EQGW_MQTT__HOST": "127.0.0.1", "EQGW_MQTT__TOPIC_PREFIX": prefix}
    proc, base = start_gateway(tmp_path, db_url, fleet, f"mqtt-{n}", extra_env=env)
    wait_until(lambda: (readyz(base) or {}).get("ready"), 120, "the gateway ready")
    return proc


def test_events_raised_before_the_publisher_started_are_published(
    engine: Engine, db_url: str, tmp_path: Path
) -> None:
    prefix = f"eqgw-test-{uuid.uuid4().hex[:8]}/alerts"
    sub = Subscriber(prefix)
    gw: Process | None = None
    try:
        # Before any gateway published: one alert raised and cleared (history), one raised.
        history = add_alert(engine, vehicle_id="BUS-1")
        old = [add_event(engine, history, "raised"), add_event(engine, history, "cleared")]
        alert = add_alert(engine, vehicle_id="BUS-2")
        raised = add_event(engine, alert, "raised")
        gw = _gateway(tmp_path, db_url, prefix, 1)
        acked = add_event(engine, alert, "acknowledged")
        wait_until(lambda: len(sub.got()) >= 2, 60, "the alert raised and acknowledged")
        assert gw.stop() in (0, -15), gw.output()[-3000:]
        # Raised while no gateway ran: published after the next start.
        cleared = add_event(engine, alert, "cleared")
        gw = _gateway(tmp_path, db_url, prefix, 2)
        wait_until(lambda: len(sub.got()) >= 3, 60, "the alert cleared")
        got = [b["event_id"] for _, b in sub.got()]
        # In order, at least once (a lost acknowledgement may repeat one), nothing of history.
        assert sorted(set(got)) == [raised, acked, cleared] and got == sorted(got)
        assert not set(old) & set(got)
        assert {t for t, _ in sub.got()} == {f"{prefix}/BUS-2/imbalance"}
    finally:
        sub.close()
        if gw is not None and gw.proc.poll() is None:
            gw.stop()
