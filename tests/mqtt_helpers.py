"""The shared Mosquitto (127.0.0.1:1883) left as a test found it: retained messages cleared."""

from __future__ import annotations

import threading
import time
from typing import Any

import paho.mqtt.client as paho
from paho.mqtt.enums import CallbackAPIVersion

BROKER = ("127.0.0.1", 1883)
QUIET_S = 0.5  # no new retained message for this long: the broker has sent them all


def clear_retained(*filters: str, broker: tuple[str, int] = BROKER) -> int:
    """Publish an empty retained message (which deletes it) to every topic under `filters`
    that holds one; returns how many."""
    topics: set[str] = set()
    last = [time.monotonic()]
    lock = threading.Lock()
    subscribed = threading.Event()

    def on_message(_c: Any, _u: Any, msg: Any) -> None:
        if msg.retain and msg.payload:
            with lock:
                topics.add(msg.topic)
                last[0] = time.monotonic()

    client = paho.Client(callback_api_version=CallbackAPIVersion.VERSION2)
    client.on_message = on_message
    client.on_subscribe = lambda *_: subscribed.set()
    client.connect(*broker)
    client.loop_start()
    try:
        client.subscribe([(f, 1) for f in filters])
        if not subscribed.wait(10):
            return 0
        last[0] = time.monotonic()
        deadline = time.monotonic() + 30
        while time.monotonic() - last[0] < QUIET_S and time.monotonic() < deadline:
            time.sleep(0.05)
        with lock:
            found = sorted(topics)
        client.unsubscribe(list(filters))
        infos = [client.publish(t, b"", qos=1, retain=True) for t in found]
        for info in infos:
            info.wait_for_publish(10)
        return len(found)
    finally:
        client.disconnect()
        client.loop_stop()
