"""Alert events over MQTT: a real subscriber on the local Mosquitto (127.0.0.1:1883)."""

from __future__ import annotations

import json
import socket
import threading
import uuid
from typing import Any

import paho.mqtt.client as paho
import pytest
from paho.mqtt.enums import CallbackAPIVersion
from sqlalchemy import Engine

from eqgw.config import DeliverySettings, MqttSettings, Settings
from eqgw.notify.delivery import AlertDelivery
from tests.api_helpers import wait_for
from tests.webhook_helpers import add_alert, add_event

BROKER = ("127.0.0.1", 1883)


def _broker_up() -> bool:
    try:
        with socket.create_connection(BROKER, timeout=2):
            return True
    except OSError:
        return False


pytestmark = pytest.mark.skipif(
    not _broker_up(), reason=f"no MQTT broker at {BROKER[0]}:{BROKER[1]}"
)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class Subscriber:
    """Collects (topic, payload) of everything under a prefix, at QoS 1."""

    def __init__(self, prefix: str) -> None:
        self.messages: list[tuple[str, Any]] = []
        self._lock = threading.Lock()
        self._subscribed = threading.Event()
        self.client = paho.Client(callback_api_version=CallbackAPIVersion.VERSION2)
        self.client.on_connect = lambda c, *_: c.subscribe(f"{prefix}/#", qos=1)
        self.client.on_subscribe = lambda *_: self._subscribed.set()
        self.client.on_message = self._on_message
        self.client.connect(*BROKER)
        self.client.loop_start()
        assert self._subscribed.wait(10), "no SUBACK from the broker"

    def _on_message(self, _c: Any, _u: Any, msg: Any) -> None:
        with self._lock:
            self.messages.append((msg.topic, json.loads(msg.payload)))

    def got(self) -> list[tuple[str, Any]]:
        with self._lock:
            return list(self.messages)

    def close(self) -> None:
        self.client.disconnect()
        self.client.loop_stop()


def gateway(engine: Engine, prefix: str, port: int = BROKER[1]) -> AlertDelivery:
    settings = Settings(
        database_url="sqlite://",
        delivery=DeliverySettings(poll_s=0.05, gap_wait_s=0.5),
        mqtt=MqttSettings(host=BROKER[0], port=port, topic_prefix=prefix, reconnect_min_s=1,
                          reconnect_max_s=2, publish_timeout_s=5),
    )  # fmt: skip
    return AlertDelivery(engine, settings, "http://depot.example")


async def test_alert_events_published_and_kept_while_the_broker_is_away(engine: Engine) -> None:
    prefix = f"eqgw-test-{uuid.uuid4().hex[:8]}/alerts"
    sub = Subscriber(prefix)
    try:
        # First start (cursor created past the history: alerts cleared before it are not
        # published), against a broker that is not there.
        history = add_alert(engine)
        before = [add_event(engine, history, "raised"), add_event(engine, history, "cleared")]
        gw = gateway(engine, prefix, port=_free_port())
        await gw.start()
        alert = add_alert(engine, vehicle_id="BUS-7", rule="overvoltage", severity="critical")
        raised = add_event(engine, alert, "raised")
        muted = add_event(engine, add_alert(engine), "raised", muted=True)
        cleared = add_event(engine, alert, "cleared")
        await wait_for(lambda: _now(gw.mqtt is not None and gw.mqtt.last_error), what="refusal")
        await gw.stop()
        assert sub.got() == []
        # Restarted with the broker reachable: what waited is published, in order.
        gw = gateway(engine, prefix)
        await gw.start()
        try:

            async def both() -> bool:
                return len(sub.got()) >= 2

            await wait_for(both, what="both alert events on the subscriber")
            later = add_event(engine, alert, "raised")

            async def third() -> bool:
                return len(sub.got()) >= 3

            await wait_for(third, what="a live event")
        finally:
            await gw.stop()
        got = sub.got()
        assert [b["event_id"] for _, b in got] == [raised, cleared, later]
        assert {t for t, _ in got} == {f"{prefix}/BUS-7/overvoltage"}
        body = got[0][1]
        assert body["event"] == "raised" and body["alert"]["severity"] == "critical"
        assert body["links"]["vehicle"] == "http://depot.example/#/vehicle/BUS-7"
        assert not {*before, muted} & {b["event_id"] for _, b in got}
    finally:
        sub.close()


async def _now(value: Any) -> Any:
    return value
