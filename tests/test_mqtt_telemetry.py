"""MQTT telemetry on the local Mosquitto (127.0.0.1:1883): retained values per unit equal to
the gateway's live state, vehicle states, Home Assistant discovery, coalescing, the broker
lost and back, and the last will of a killed gateway among two on PostgreSQL."""

from __future__ import annotations

import json
import struct
import sys
import threading
import time
import uuid
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import paho.mqtt.client as paho
import paho.mqtt.publish as publish
import pytest
from paho.mqtt.enums import CallbackAPIVersion

from eqgw.config import ConfigError, load_settings
from eqgw.notify.telemetry import UNIT_SENSORS, TelemetryPublisher
from tests.api_helpers import Served, served, wait_for
from tests.cluster_helpers import (
    METRICS_TOKEN,
    operator_key,
    readyz,
    start_gateway,
    start_simulator,
    write_fleet,
)
from tests.mqtt_helpers import clear_retained
from tests.proc_helpers import Process, wait_until
from tests.proxy_helpers import BlackholeProxy
from tests.support import web
from tests.test_webhooks_mqtt import BROKER, pytestmark  # noqa: F401 (skip: no broker)

NUMBERS = (
    "v12", "v24", "i12", "i24", "battery_a_v", "battery_b_v", "imbalance_v",
    "soc_12v", "soc_24v", "soh_12v", "soh_24v", "last_seen", "parked_since",
)  # fmt: skip


class Watch:
    """Every message under some topic filters, as (topic, payload, retained, monotonic time),
    from a subscriber of its own."""

    def __init__(self, *filters: str) -> None:
        self.messages: list[tuple[str, bytes, bool, float]] = []
        self._lock = threading.Lock()
        self._subscribed = threading.Event()
        self.client = paho.Client(callback_api_version=CallbackAPIVersion.VERSION2)
        self.client.on_connect = lambda c, *_: c.subscribe([(f, 1) for f in filters])
        self.client.on_subscribe = lambda *_: self._subscribed.set()
        self.client.on_message = self._on_message
        self.client.connect(*BROKER)
        self.client.loop_start()
        assert self._subscribed.wait(10), "no SUBACK from the broker"

    def _on_message(self, _c: Any, _u: Any, msg: Any) -> None:
        with self._lock:
            self.messages.append((msg.topic, bytes(msg.payload), msg.retain, time.monotonic()))

    def all(self, prefix: str = "") -> list[tuple[str, bytes, bool, float]]:
        with self._lock:
            return [m for m in self.messages if m[0].startswith(prefix)]

    def latest(self, prefix: str = "") -> dict[str, bytes]:
        """The last payload of each topic under `prefix`."""
        return {topic: payload for topic, payload, *_ in self.all(prefix)}

    def json(self, prefix: str = "") -> dict[str, Any]:
        return {t: json.loads(p) for t, p in self.latest(prefix).items() if p}

    def close(self) -> None:
        self.client.disconnect()
        self.client.loop_stop()


@pytest.fixture
def prefix() -> Iterator[str]:
    """A topic prefix of the test's own; its retained topics are cleared afterwards."""
    name = f"eqgw-test-{uuid.uuid4().hex[:8]}"
    yield name
    clear_retained(f"{name}/#", f"{name}-ha/#")


def _telemetry(prefix: str, **over: Any) -> dict[str, Any]:
    return {
        "mqtt": {
            "host": BROKER[0],
            "port": over.pop("port", BROKER[1]),
            "keepalive_s": over.pop("keepalive_s", 30),
            "reconnect_min_s": 1,
            "reconnect_max_s": 2,
            "telemetry": {
                "enabled": True,
                "topic_prefix": prefix,
                "discovery_prefix": f"{prefix}-ha",
                "gateway_id": "gw-test",
                **over,
            },
        }
    }


def _units(s: Served) -> list[tuple[str, str, int]]:
    return sorted((u.ref.vehicle_id, u.ref.bus, u.ref.sa) for u in s.rt.ingest.live.units.values())


def _unit_topic(prefix: str, vid: str, bus: str, sa: int) -> str:
    return f"{prefix}/vehicles/{vid}/units/{bus.replace('/', '_')}/{sa}"


def _expected(vid: str, unit: dict[str, Any], gateway: str) -> dict[str, Any]:
    """A unit's topic as `GET /vehicles/{id}/live` gives its values."""
    summary, diag = unit["summary"], unit["diagnosis"]
    volts = unit["latest"].get("voltages", {}).get("fields", {})
    return {
        "vehicle_id": vid,
        "bus": unit["bus"],
        "sa": unit["sa"],
        "series": unit["series"],
        "model": unit["model"],
        "state": unit["state"],
        "last_seen": unit["last_seen"],
        "parked_since": unit["parked_since"],
        "v12": volts.get("v12"),
        "v24": volts.get("v24"),
        "i12": volts.get("i12"),
        "i24": volts.get("i24"),
        "battery_a_v": diag["battery_a_v"],
        "battery_b_v": diag["battery_b_v"],
        "imbalance_v": summary["imbalance_v"],
        "soc_12v": summary["soc_12v"],
        "soc_24v": summary["soc_24v"],
        "soh_12v": summary["soh_12v"],
        "soh_24v": summary["soh_24v"],
        "diagnosis": summary["diagnosis"]["condition"],
        "active_faults": summary["active_faults"],
        "status": unit["status_flags"],
        "gateway": gateway,
    }


def _bits(value: Any) -> Any:
    return struct.pack("<d", value).hex() if isinstance(value, float) else value


def test_telemetry_needs_a_broker(tmp_path: Path) -> None:
    fleet = tmp_path / "fleet.toml"
    fleet.write_text("[mqtt.telemetry]\nenabled = true\n")
    with pytest.raises(ConfigError, match=r"mqtt.telemetry.enabled needs mqtt.host"):
        load_settings(fleet)
    fleet.write_text('[mqtt]\nhost = "b"\n[mqtt.telemetry]\nenabled = true\ntopic_prefix = "a/+"\n')
    with pytest.raises(ConfigError, match=r"mqtt.telemetry.topic_prefix"):
        load_settings(fleet)
    settings = load_settings(None, mqtt={"host": "b"})
    assert settings.mqtt.telemetry.enabled is False  # off unless asked for


async def test_retained_values_equal_the_live_state_bit_for_bit(
    sqlite_url: str, prefix: str
) -> None:
    watch = Watch(f"{prefix}/#")
    try:
        async with served(sqlite_url, config=_telemetry(prefix, interval_s=0.5)) as s:
            units = _units(s)
            topics = {_unit_topic(prefix, *u): u for u in units}
            status = f"{prefix}/gateways/gw-test/status"

            async def every_unit() -> bool:
                got = watch.latest()
                if got.get(status) != b"online" or not set(topics) <= set(got):
                    return False
                # Identified too: a unit parked before it answered the gateway's request for
                # its identity stays without a series (the series are checked below).
                values = watch.json(f"{prefix}/vehicles")
                return all(values.get(t, {}).get("series") is not None for t in topics)

            await wait_for(every_unit, what="the status and every unit's topic, identified")
            # Ignition off everywhere: the values stop where they are, the units park.
            for vid in s.sim.names:
                s.sim.ignition_off(vid)
            vehicles = sorted({u[0] for u in units})

            async def all_parked() -> bool:
                got = watch.json(f"{prefix}/vehicles")
                return all(got.get(t, {}).get("state") == "parked" for t in topics) and all(
                    got.get(f"{prefix}/vehicles/{v}/state", {}).get("state") == "parked"
                    for v in vehicles
                )

            await wait_for(all_parked, what="every unit and vehicle parked on MQTT")
            got = watch.json(f"{prefix}/vehicles")
            for vid in vehicles:
                r = await s.client.get(f"/api/v1/vehicles/{vid}/live", headers=s.auth())
                assert r.status_code == 200
                live = r.json()
                assert got[f"{prefix}/vehicles/{vid}/state"] == {
                    "vehicle_id": vid, "name": vid, "depot": "simulated", "state": live["state"],
                    "parked_since": live["parked_since"], "gateway": "gw-test",
                }  # fmt: skip
                for unit in live["units"]:
                    topic = _unit_topic(prefix, vid, unit["bus"], unit["sa"])
                    want = _expected(vid, unit, "gw-test")
                    assert got[topic] == want
                    assert {k: _bits(got[topic][k]) for k in NUMBERS} == {
                        k: _bits(want[k]) for k in NUMBERS
                    }
                    assert want["v12"] is not None and want["status"]
            # The series tell: the 70-series unit has no currents, SOC nor SOH.
            series = {t: v["series"] for t, v in got.items() if t in topics}
            assert {70, 80} <= set(series.values())
            for t, v in got.items():
                if t in topics and v["series"] == 70:
                    assert v["i12"] is v["soc_12v"] is v["soh_24v"] is None
            # What a subscriber arriving now is given: the same, retained.
            late = Watch(f"{prefix}/#")
            try:

                async def retained() -> bool:
                    return set(topics) | {status} <= set(late.latest())

                await wait_for(retained, what="the retained topics")
                assert all(r for t, _, r, _ in late.all() if t in topics)
                assert {t: late.json(f"{prefix}/vehicles")[t] for t in topics} == {
                    t: got[t] for t in topics
                }
            finally:
                late.close()
            # Reported: /readyz and /metrics.
            ready = (await s.client.get("/readyz", headers=s.auth())).json()
            tel = ready["telemetry"]
            assert tel["connected"] and tel["gateway_id"] == "gw-test"
            assert tel["status_topic"] == status and tel["published"]["unit"] >= len(units)
            metrics = (await s.client.get("/metrics", headers=s.auth())).text
            assert "eqgw_mqtt_telemetry_connected 1.0" in metrics
            assert 'eqgw_mqtt_telemetry_published_total{kind="unit"}' in metrics
            # An `offline` while it is connected (a late will of its own, another process
            # of the same name) is answered: the status topic says online again.
            mark = time.monotonic()
            publish.single(status, "offline", qos=1, retain=True, hostname=BROKER[0])

            async def reasserted() -> bool:
                said = [p for t, p, _, at in watch.all(status) if at > mark]
                return said[-2:] == [b"offline", b"online"]

            await wait_for(reasserted, what="online again")
        # A clean stop says offline (the last will is for an unclean one).
        await wait_for(lambda: _now(watch.latest().get(status) == b"offline"), what="offline")
    finally:
        watch.close()


async def test_home_assistant_discovery_configs(sqlite_url: str, prefix: str) -> None:
    jinja2 = pytest.importorskip("jinja2")
    ha = f"{prefix}-ha"
    watch = Watch(f"{prefix}/#", f"{ha}/#")
    try:
        config = _telemetry(prefix, interval_s=0.5, homeassistant=True)
        async with served(sqlite_url, config=config) as s:
            units = _units(s)
            status = f"{prefix}/gateways/gw-test/status"

            def series() -> dict[tuple[str, int], int | None]:
                return {(u.ref.bus, u.ref.sa): u.series for u in s.rt.ingest.live.units.values()}

            # 13 sensors per 80-series unit, 7 per 70-series one, a state per vehicle.
            def wanted() -> int:
                known = series()
                return sum(
                    len(UNIT_SENSORS) if known[(bus, sa)] == 80 else 7 for _, bus, sa in units
                ) + len(s.sim.names)

            async def announced() -> bool:
                known = None not in series().values()
                return known and len(watch.json(f"{ha}/")) >= wanted()

            await wait_for(announced, what="every unit's series and discovery config")
            await wait_for(lambda: _now(len(watch.json(f"{ha}/")) == wanted()), what="no more")
            series_of = series()
            late = Watch(f"{ha}/#")  # what Home Assistant finds when it starts: all retained
            try:
                # Equal to the last config published on each topic (a unit's config is
                # published again when its component ID arrives and names its model, which
                # on a loaded machine can come after the count is complete).
                await wait_for(
                    lambda: _now(late.json() == watch.json(f"{ha}/")), what="retained configs"
                )
                assert all(r for *_, r, _ in late.all())
            finally:
                late.close()
            configs = watch.json(f"{ha}/")
            values = watch.json(f"{prefix}/vehicles")
            uids = [c["unique_id"] for c in configs.values()]
            assert len(set(uids)) == len(uids)
            env = jinja2.Environment()
            by_state_topic: dict[str, set[str]] = {}
            for topic, c in configs.items():
                assert topic == f"{ha}/sensor/{c['unique_id']}/config"
                for field in ("name", "unique_id", "state_topic", "value_template", "device"):
                    assert c[field], (topic, field)
                assert c["availability_topic"] == status
                assert (c["payload_available"], c["payload_not_available"]) == (
                    "online",
                    "offline",
                )
                assert c["device"]["identifiers"] and c["device"]["name"]
                assert c["origin"]["name"] == "eqgw"
                if c.get("device_class") == "enum":
                    assert c["options"] and "unit_of_measurement" not in c
                else:
                    assert c["unit_of_measurement"] in ("V", "A", "%")
                    assert c["state_class"] == "measurement"
                    assert c.get("device_class") in ("voltage", "current", "battery", None)
                # The template reads the value out of the state topic's payload.
                key = c["value_template"].split("value_json.")[1].split()[0]
                payload = values[c["state_topic"]]
                rendered = env.from_string(c["value_template"]).render(value_json=payload)
                assert rendered == str(payload[key]), (topic, rendered)
                if c.get("device_class") == "enum":
                    assert payload[key] in c["options"]
                by_state_topic.setdefault(c["state_topic"], set()).add(key)
            for vid, bus, sa in units:
                keys = by_state_topic[_unit_topic(prefix, vid, bus, sa)]
                base = {"v12", "v24", "battery_a_v", "battery_b_v", "imbalance_v", "state"}
                assert base | {"diagnosis"} <= keys
                eighty = {"i12", "i24", "soc_12v", "soc_24v", "soh_12v", "soh_24v"}
                assert (eighty <= keys) if series_of[(bus, sa)] == 80 else not (eighty & keys)
            for vid in s.sim.names:
                assert by_state_topic[f"{prefix}/vehicles/{vid}/state"] == {"state"}
            # A unit's device hangs off its vehicle's.
            vehicle_ids = {
                c["device"]["identifiers"][0]
                for c in configs.values()
                if c["state_topic"].endswith("/state")
            }
            assert {
                c["device"]["via_device"]
                for c in configs.values()
                if not c["state_topic"].endswith("/state")
            } <= vehicle_ids
    finally:
        watch.close()


async def test_coalesced_and_republished_after_the_broker_is_back(
    sqlite_url: str, prefix: str
) -> None:
    proxy = BlackholeProxy(BROKER)
    watch = Watch(f"{prefix}/#")
    interval = 1.0
    config = _telemetry(prefix, port=proxy.port, keepalive_s=5, interval_s=interval)
    try:
        async with served(sqlite_url, config=config) as s:
            tel: TelemetryPublisher = s.app.state.telemetry
            topics = [_unit_topic(prefix, *u) for u in _units(s)]
            status = f"{prefix}/gateways/gw-test/status"

            async def streamed() -> bool:
                return all(len(watch.all(t)) >= 6 for t in topics)

            await wait_for(streamed, what="six publishes of every unit")
            # Each unit at most once per interval, whatever its frames (several a second).
            for t in topics:
                got = [at for topic, *_, at in watch.all(t) if topic == t]
                assert len(got) <= (got[-1] - got[0]) / interval + 2, (t, got)
            assert tel.counters.changes > tel.counters.published["unit"]

            # The broker unreachable (no byte passes, no reset): the broker says the
            # gateway is offline (its last will), nothing piles up, and once back
            # everything is published again.
            proxy.blackhole()
            await wait_for(lambda: _now(not tel.connected), 60, "the loss noticed")
            await wait_for(
                lambda: _now(watch.latest().get(status) == b"offline"), 60, "the last will"
            )
            ready = (await s.client.get("/readyz", headers=s.auth())).json()
            assert ready["telemetry"]["connected"] is False
            assert ready["telemetry"]["last_error"]
            assert len(tel._dirty_units) <= len(topics)  # one entry per unit: latest wins
            assert len(tel._pending) <= tel.telemetry.max_pending
            back = time.monotonic()
            proxy.restore()

            async def republished() -> bool:
                after = [(t, at) for t, _, _, at in watch.all() if at > back]
                return (status, b"online") in [
                    (t, p) for t, p, _, at in watch.all() if at > back
                ] and set(topics) <= {t for t, _ in after}

            await wait_for(republished, 60, "online again and every unit republished")
    finally:
        watch.close()
        proxy.close()


async def _now(value: Any) -> Any:
    return value


# -- two gateways on PostgreSQL: each publishes its own buses; a killed one's last will ----------

BUSES = [f"SIM-00{i}" for i in range(1, 5)]


@pytest.fixture
def pg_fleet(tmp_path: Path, pg_url: str) -> Iterator[tuple[Path, str]]:
    operator_key(pg_url, "telemetry test")
    sim, port = start_simulator(tmp_path, len(BUSES))
    try:
        yield write_fleet(tmp_path / "fleet.toml", BUSES, port), pg_url
    finally:
        sim.stop()


def _owned(base: str) -> set[str]:
    body = readyz(base) or {}
    return set((body.get("cluster") or {}).get("owned", []))


@pytest.mark.postgres
def test_each_gateway_publishes_its_buses_and_a_killed_one_is_offline(
    tmp_path: Path, pg_fleet: tuple[Path, str], prefix: str
) -> None:
    fleet, pg_url = pg_fleet
    ha = f"{prefix}-ha"
    env = {
        "EQGW_MQTT__HOST": BROKER[0],
        "EQGW_MQTT__TELEMETRY__ENABLED": "true",
        "EQGW_MQTT__TELEMETRY__TOPIC_PREFIX": prefix,
        "EQGW_MQTT__TELEMETRY__INTERVAL_S": "0.5",
        "EQGW_MQTT__TELEMETRY__HOMEASSISTANT": "true",
        "EQGW_MQTT__TELEMETRY__DISCOVERY_PREFIX": ha,
    }
    watch = Watch(f"{prefix}/#", f"{ha}/#")
    gw: dict[str, tuple[Process, str]] = {}
    try:
        # No gateway_id set: each is named by its EQGW_CLUSTER_INSTANCE_ID.
        for name in ("gw-a", "gw-b"):
            gw[name] = start_gateway(tmp_path, pg_url, fleet, name, extra_env=env)
        a, b = gw["gw-a"][1], gw["gw-b"][1]

        def balanced() -> bool:
            oa, ob = _owned(a), _owned(b)
            return len(oa) == 2 and len(ob) == 2 and oa | ob == set(BUSES)

        wait_until(balanced, 90, "both gateways up with two buses each")
        owner = dict.fromkeys(_owned(a), "gw-a") | dict.fromkeys(_owned(b), "gw-b")
        status = {n: f"{prefix}/gateways/{n}/status" for n in gw}

        def units() -> dict[str, Any]:
            return {t: v for t, v in watch.json(f"{prefix}/vehicles").items() if "/units/" in t}

        def published_by(owners: dict[str, str]) -> bool:
            got = units()
            # One unit per bus (the fleet file reads SA 30 alone).
            return len(got) == len(BUSES) and all(
                v["gateway"] == owners[v["bus"]] for v in got.values()
            )

        wait_until(lambda: published_by(owner), 60, "every unit published by its bus's reader")
        assert {watch.latest().get(s) for s in status.values()} == {b"online"}

        def availability(owners: dict[str, str]) -> bool:
            configs = watch.json(f"{ha}/")
            by_unit = {
                c["state_topic"]: c["availability_topic"]
                for c in configs.values()
                if "/units/" in c["state_topic"]
            }
            return len(by_unit) == len(BUSES) and all(
                topic == status[owners[units()[unit]["bus"]]] for unit, topic in by_unit.items()
            )

        wait_until(lambda: availability(owner), 60, "discovery naming each reader's status")

        # SIGKILL B: the broker publishes its last will; A takes its buses over and
        # publishes their units, naming itself as their availability.
        gw["gw-b"][0].kill()
        wait_until(lambda: watch.latest().get(status["gw-b"]) == b"offline", 60, "B's last will")
        everything_a = dict.fromkeys(BUSES, "gw-a")
        wait_until(lambda: published_by(everything_a), 90, "every unit published by A")
        wait_until(lambda: availability(everything_a), 30, "discovery naming A")
        assert watch.latest().get(status["gw-a"]) == b"online"
        late = Watch(f"{prefix}/gateways/#")
        try:
            wait_until(lambda: len(late.latest()) == 2, 30, "both status topics, retained")
            assert late.latest() == {status["gw-a"]: b"online", status["gw-b"]: b"offline"}
            assert all(r for *_, r, _ in late.all())
        finally:
            late.close()
        body = web.get(
            f"{a}/readyz", headers={"Authorization": f"Bearer {METRICS_TOKEN}"}, timeout=10
        ).json()
        assert body["telemetry"]["gateway_id"] == "gw-a" and body["telemetry"]["connected"]
    except AssertionError:
        vehicles = watch.json(f"{prefix}/vehicles").items()
        got = {t: (v.get("gateway"), v.get("bus")) for t, v in vehicles}
        sys.stderr.write(f"published: {got}\nstatus: {watch.latest(f'{prefix}/gateways')}\n")
        for name, (proc, base) in gw.items():
            sys.stderr.write(f"--- {name}: readyz {readyz(base)}\n{proc.output()[-3000:]}\n")
        raise
    finally:
        for proc, _ in gw.values():
            if proc.proc.poll() is None:
                proc.stop()
        watch.close()
