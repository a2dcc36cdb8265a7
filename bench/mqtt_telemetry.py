"""MQTT telemetry of a streaming fleet: what reaches the broker, against what changed.

    python -m bench.mqtt_telemetry [--vehicles 500] [--seconds 30] [--interval 5]
                                   [--homeassistant] [--broker 127.0.0.1:1883]

`eqgw serve --simulate N` in-process (SQLite in a temporary folder, the simulator at real
speed) with `mqtt.telemetry` on, and a subscriber on the broker. Prints how long the first
round took (every unit, and its discovery configs with --homeassistant), then over the
measured seconds: live changes per second on the units read, messages and bytes per second
reaching the subscriber by kind, the most messages any one unit topic got (the interval's
bound), and the largest number of messages waiting in the client. Its retained topics are
cleared at the end.
"""

from __future__ import annotations

import argparse
import asyncio
import shutil
import sys
import tempfile
import threading
import time
import uuid
from collections import Counter
from pathlib import Path
from typing import Any

import paho.mqtt.client as paho
from paho.mqtt.enums import CallbackAPIVersion

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from eqgw.config import Settings
from eqgw.main import create_app
from eqgw.notify.telemetry import TelemetryPublisher
from eqgw.sim.clock import RealtimeClock
from eqgw.sim.fleet import SimulatedFleet
from tests.mqtt_helpers import clear_retained


class Counting:
    """A subscriber counting messages and bytes per topic, from a given moment."""

    def __init__(self, host: str, port: int, *filters: str) -> None:
        self.lock = threading.Lock()
        self.since = float("inf")
        self.messages: Counter[str] = Counter()
        self.bytes: Counter[str] = Counter()
        self.first_seen: dict[str, float] = {}
        self.ready = threading.Event()
        self.client = paho.Client(callback_api_version=CallbackAPIVersion.VERSION2)
        self.client.on_connect = lambda c, *_: c.subscribe([(f, 0) for f in filters])
        self.client.on_subscribe = lambda *_: self.ready.set()
        self.client.on_message = self._on_message
        self.client.connect(host, port)
        self.client.loop_start()
        if not self.ready.wait(10):
            raise SystemExit(f"no broker answering at {host}:{port}")

    def _on_message(self, _c: Any, _u: Any, msg: Any) -> None:
        now = time.monotonic()
        with self.lock:
            self.first_seen.setdefault(msg.topic, now)
            if now >= self.since:
                self.messages[msg.topic] += 1
                self.bytes[msg.topic] += len(msg.payload)

    def start(self) -> None:
        with self.lock:
            self.since = time.monotonic()
            self.messages.clear()
            self.bytes.clear()

    def stop(self) -> None:
        with self.lock:
            self.since = float("inf")

    def close(self) -> None:
        self.client.disconnect()
        self.client.loop_stop()


def kind(topic: str) -> str:
    if "/units/" in topic:
        return "unit"
    if topic.endswith("/state") and "/vehicles/" in topic:
        return "vehicle"
    if topic.endswith("/config"):
        return "discovery"
    return "status"


async def run(args: argparse.Namespace) -> None:
    host, _, port_s = args.broker.partition(":")
    port = int(port_s or 1883)
    prefix = f"eqgw-bench-{uuid.uuid4().hex[:8]}"
    ha = f"{prefix}-ha"
    watch = Counting(host, port, f"{prefix}/#", f"{ha}/#")
    tmp = Path(tempfile.mkdtemp(prefix="eqgw-bench-mqtt-"))
    sim = SimulatedFleet(args.vehicles, seed=1, clock=RealtimeClock())
    telemetry = {
        "enabled": True,
        "topic_prefix": prefix,
        "interval_s": args.interval,
        "homeassistant": args.homeassistant,
        "discovery_prefix": ha,
        "gateway_id": "bench",
    }
    settings = Settings(
        database_url=f"sqlite:///{tmp / 'eqgw.db'}",
        mqtt={"host": host, "port": port, "telemetry": telemetry},
    )
    app = create_app(settings, sim=sim)
    started = time.monotonic()
    try:
        async with app.router.lifespan_context(app):
            tel: TelemetryPublisher = app.state.telemetry
            units = sum(len(v.spec.units) for v in sim.vehicles.values())
            while len(app.state.rt.ingest.live.units) < units:
                await asyncio.sleep(0.5)
            # The first round: every unit's topic (and its configs) reaches the subscriber.
            while sum(1 for t in watch.first_seen if kind(t) == "unit") < units:
                if time.monotonic() - started > 600:
                    raise SystemExit("not every unit was published within 600 s")
                await asyncio.sleep(0.2)
            first = max(watch.first_seen.values()) - min(watch.first_seen.values())
            configs = sum(1 for t in watch.first_seen if kind(t) == "discovery")
            print(
                f"{args.vehicles} vehicles, {units} units: first round {first:.1f} s "
                f"({units} unit topics, {configs} discovery configs)",
                flush=True,
            )
            # Steady state: every unit's series learned (its discovery configs complete),
            # then an interval past the burst.
            live = app.state.rt.ingest.live
            while any(u.series is None for u in live.units.values()):
                await asyncio.sleep(0.5)
            await asyncio.sleep(args.interval)
            changes0, pending_max = tel.counters.changes, 0
            watch.start()
            t0 = time.monotonic()
            while time.monotonic() - t0 < args.seconds:
                pending_max = max(pending_max, len(tel._pending))
                await asyncio.sleep(0.1)
            took = time.monotonic() - t0
            watch.stop()
            changes = tel.counters.changes - changes0
            c = tel.counters
            print(
                f"connections {tel.sessions}, refused {c.refused}, deferred {c.deferred}, "
                f"resyncs {c.resyncs}"
            )
    finally:
        watch.close()
        shutil.rmtree(tmp, ignore_errors=True)
        clear_retained(f"{prefix}/#", f"{ha}/#", broker=(host, port))
    with watch.lock:
        messages, sizes = dict(watch.messages), dict(watch.bytes)
    by_kind: Counter[str] = Counter()
    bytes_kind: Counter[str] = Counter()
    for t, n in messages.items():
        by_kind[kind(t)] += n
        bytes_kind[kind(t)] += sizes[t]
    per_unit = [n for t, n in messages.items() if kind(t) == "unit"]
    print(
        f"over {took:.0f} s, interval {args.interval:g} s: live changes {changes / took:.0f}/s; "
        f"to the broker {sum(by_kind.values()) / took:.0f} messages/s, "
        f"{sum(bytes_kind.values()) / took / 1000:.0f} kB/s ("
        + ", ".join(
            f"{k} {by_kind[k] / took:.1f}/s" for k in ("unit", "vehicle", "discovery", "status")
        )
        + ")"
    )
    bound = int(took / args.interval) + 1
    print(
        f"per unit topic: at most {max(per_unit, default=0)} messages "
        f"(the interval allows {bound}), mean payload "
        f"{bytes_kind['unit'] / max(1, by_kind['unit']):.0f} B; "
        f"most messages waiting in the client: {pending_max}"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--vehicles", type=int, default=500)
    parser.add_argument("--seconds", type=float, default=30.0)
    parser.add_argument("--interval", type=float, default=5.0)
    parser.add_argument("--homeassistant", action="store_true")
    parser.add_argument("--broker", default="127.0.0.1:1883")
    asyncio.run(run(parser.parse_args()))


if __name__ == "__main__":
    main()
