"""Live values to MQTT: a retained topic per unit and per vehicle, the gateway's availability
as a last will, and Home Assistant discovery (docs/mqtt.md).

Topics (`<prefix>` is `mqtt.telemetry.topic_prefix`, names made single topic levels):

- `<prefix>/gateways/<gateway>/status`: `online` (published at every connection) or `offline`
  (at a clean stop, and by the broker as this connection's last will when the process dies or
  its link does), retained, QoS 1.
- `<prefix>/vehicles/<vehicle>/units/<bus>/<sa>`: one JSON object with the unit's latest
  values (`UnitValues`), retained. One topic per unit rather than one per signal: a unit's
  values of one moment arrive together (battery B is V24 - V12 of one frame), a subscriber or
  Home Assistant reads every sensor from one message, and 500 units cost 500 messages per
  interval instead of 15 times as many.
- `<prefix>/vehicles/<vehicle>/state`: the vehicle's state (`VehicleState`), retained,
  published when it changes.

Rate: the ingest's hub marks a unit (and its vehicle) dirty on each change; a round every
`TICK_S` (at most half the interval) publishes each dirty unit whose last publish is at least
`interval_s` old, built from the live state then: a unit streaming every second is published
once per interval with its latest values, whatever the fleet's size. Nothing queues per
change: the dirty set holds each unit once (latest value wins). Messages handed to paho and
not yet written (QoS 0) or acknowledged (QoS 1) are bounded by `max_pending`; past it the
round stops and the rest wait, dirty, for the next one. While the broker is away nothing is
published; at every (re)connection the gateway says `online` and publishes every unit and
vehicle it reads again (a broker restarted without persistence has lost its retained
messages), discovery included. Every `SWEEP_S` each unit and vehicle is looked at again (a
state can change with time alone); a payload the same as the last one sent is not sent.

Several gateways on one database: each publishes the units of the buses it reads (and of the
edge-forwarded streams it receives), never those it mirrors from the others (their events are
`RemoteEvent`s), and a vehicle's state is published by the gateway that reads its lead unit
(its lowest bus and SA). Its discovery configs name its own status topic as availability, and
a gateway that takes a bus over publishes them again, naming its own.

Threads: paho's network thread connects, reconnects with backoff and runs the callbacks,
which only set plain attributes and call paho (`online` at each connection, and again when
an `offline` reaches the status topic while connected: a late will of its own);
the supervised asyncio loop reads the live state, which only the event loop touches, and
hands messages to paho's thread-safe `publish`.
"""

from __future__ import annotations

import asyncio
import contextlib
import hashlib
import logging
import re
import socket
import time
import uuid
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import orjson
import paho.mqtt.client as paho
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily
from prometheus_client.registry import Collector

from eqgw import version
from eqgw.cluster.fanout import is_remote
from eqgw.fleet.diagnosis import CONDITIONS, diagnose
from eqgw.ingest import events
from eqgw.ingest.events import Event, UnitRef
from eqgw.ingest.hub import EventHub, SubscriberLagged, Subscription
from eqgw.ingest.state import (
    UNIT_OFFLINE,
    UNIT_ONLINE,
    UNIT_PARKED,
    VEHICLE_STATES,
    LiveState,
    UnitState,
    vehicle_status,
)
from eqgw.jsontypes import JSONObject
from eqgw.notify.mqtt import give_up_connecting, new_client, refused_for_good, topic_level

if TYPE_CHECKING:
    from prometheus_client.metrics_core import Metric

    from eqgw.config import MqttSettings

log = logging.getLogger(__name__)

TICK_S = 0.5  # the longest a change waits for a round (rounds run at least twice per interval)
# Every so often each unit and vehicle read here is looked at again, changed or not: a state
# can change with time alone (a forwarded stream going stale); unchanged topics are not sent.
SWEEP_S = 30.0
ONLINE, OFFLINE = "online", "offline"
STOP_PUBLISH_S = 1.0  # at a stop: the wait for the broker to take `offline`
STOP_LOOP_S = 3.0  # at a stop: the wait for paho's network thread to end
# What changes a unit's topic (every ingest kind but the raw decode stream).
UNIT_KINDS = events.UNIT_KINDS
UNIT_STATES = (UNIT_ONLINE, UNIT_OFFLINE, UNIT_PARKED)
_SLOT_SOC = {"soc_12v": "battery_states/2", "soc_24v": "battery_states/4"}
_SLOT_SOH = {"soh_12v": "battery_states/1", "soh_24v": "battery_states/3"}
_NOT_ID = re.compile(r"[^A-Za-z0-9_-]")


def gateway_id(configured: str | None, cluster_instance: str | None) -> str:
    """This gateway's name in its status topic: `mqtt.telemetry.gateway_id`, else the
    cluster instance id when one was given (`EQGW_CLUSTER_INSTANCE_ID`), else the host name
    (stable across restarts, unlike the default instance id `hostname-pid`)."""
    return configured or cluster_instance or socket.gethostname()


# -- payloads ------------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class UnitValues:
    """A unit's topic: its latest values as decoded (the numbers of `GET /vehicles/{id}/live`:
    v12 ... i24 are the `voltages` record's, battery A/B and the imbalance its diagnosis's,
    SOC and SOH the `battery_states` records', null where the unit has not sent them or,
    70-series, never does), its state and where it is read."""

    vehicle_id: str
    bus: str
    sa: int
    series: int | None
    model: str | None
    state: str  # online, offline, parked
    last_seen: float | None
    parked_since: float | None
    v12: float | None
    v24: float | None
    i12: float | None
    i24: float | None
    battery_a_v: float | None
    battery_b_v: float | None
    imbalance_v: float | None  # battery B - battery A
    soc_12v: float | None
    soc_24v: float | None
    soh_12v: float | None
    soh_24v: float | None
    diagnosis: str  # the troubleshooting table's condition (eqgw.fleet.diagnosis.CONDITIONS)
    active_faults: tuple[str, ...]
    status: JSONObject | None  # the 16 status flags of its latest status frame
    gateway: str  # the gateway publishing it (the one reading its bus)


@dataclass(frozen=True, slots=True)
class VehicleState:
    """A vehicle's state topic: ok, attention, offline, parked or not_reporting (the
    dashboard's), since when it is parked, and the gateway publishing it."""

    vehicle_id: str
    name: str
    depot: str | None
    state: str
    parked_since: float | None
    gateway: str


def _fields(st: UnitState, slot: str) -> dict[str, Any]:
    hit = st.latest.get(slot)
    return hit[1] if hit else {}


def unit_values(st: UnitState, gateway: str, now: float | None = None) -> UnitValues:
    """The unit's topic payload from its live state now."""
    volts = _fields(st, "voltages")
    diag = diagnose(volts or None, st.status_flags)
    return UnitValues(
        vehicle_id=st.ref.vehicle_id,
        bus=st.ref.bus,
        sa=st.ref.sa,
        series=st.series,
        model=st.model,
        state=st.state(now),
        last_seen=st.last_seen,
        parked_since=st.faults.parked_since,
        v12=volts.get("v12"),
        v24=volts.get("v24"),
        i12=volts.get("i12"),
        i24=volts.get("i24"),
        battery_a_v=diag["battery_a_v"],
        battery_b_v=diag["battery_b_v"],
        imbalance_v=diag["b_minus_a_v"],
        soc_12v=_fields(st, _SLOT_SOC["soc_12v"]).get("soc"),
        soc_24v=_fields(st, _SLOT_SOC["soc_24v"]).get("soc"),
        soh_12v=_fields(st, _SLOT_SOH["soh_12v"]).get("soh"),
        soh_24v=_fields(st, _SLOT_SOH["soh_24v"]).get("soh"),
        diagnosis=diag["condition"],
        active_faults=tuple(sorted(st.faults.open)),
        status=st.status_flags,
        gateway=gateway,
    )


# -- topics --------------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class Topics:
    """The telemetry's topic layout under one prefix, for one gateway."""

    prefix: str
    gateway: str

    @property
    def status(self) -> str:
        return f"{self.prefix}/gateways/{topic_level(self.gateway)}/status"

    def vehicle(self, vehicle_id: str) -> str:
        return f"{self.prefix}/vehicles/{topic_level(vehicle_id)}/state"

    def unit(self, ref: UnitRef) -> str:
        vehicle, bus = topic_level(ref.vehicle_id), topic_level(ref.bus)
        return f"{self.prefix}/vehicles/{vehicle}/units/{bus}/{ref.sa}"


# -- Home Assistant discovery --------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class Sensor:
    """One Home Assistant sensor read from a unit's (or vehicle's) topic."""

    key: str  # the payload's field
    name: str
    unit: str | None = None
    device_class: str | None = None
    precision: int | None = None
    options: tuple[str, ...] | None = None  # an enum sensor's states
    series_80: bool = False  # the 80-series alone reports it

    def config(self) -> dict[str, Any]:
        out: dict[str, Any] = {
            "name": self.name,
            "value_template": f"{{{{ value_json.{self.key} }}}}",
        }
        if self.options is not None:
            out["device_class"] = "enum"
            out["options"] = list(self.options)
            return out
        out["unit_of_measurement"] = self.unit
        if self.device_class is not None:
            out["device_class"] = self.device_class
        out["state_class"] = "measurement"
        if self.precision is not None:
            out["suggested_display_precision"] = self.precision
        return out


UNIT_SENSORS = (
    Sensor("v12", "V12", "V", "voltage", 3),
    Sensor("v24", "V24", "V", "voltage", 3),
    Sensor("battery_a_v", "Battery A", "V", "voltage", 3),
    Sensor("battery_b_v", "Battery B", "V", "voltage", 3),
    Sensor("imbalance_v", "Imbalance B-A", "V", "voltage", 3),
    Sensor("i12", "Current 12 V", "A", "current", 2, series_80=True),
    Sensor("i24", "Current 24 V", "A", "current", 2, series_80=True),
    Sensor("soc_12v", "SOC 12 V battery", "%", "battery", 1, series_80=True),
    Sensor("soc_24v", "SOC 24 V battery", "%", "battery", 1, series_80=True),
    Sensor("soh_12v", "SOH 12 V battery", "%", None, 1, series_80=True),
    Sensor("soh_24v", "SOH 24 V battery", "%", None, 1, series_80=True),
    Sensor("state", "Unit state", options=UNIT_STATES),
    Sensor("diagnosis", "Diagnosis", options=CONDITIONS),
)
VEHICLE_SENSOR = Sensor("state", "State", options=VEHICLE_STATES)


def object_id(*parts: object) -> str:
    """A discovery topic level and unique id from names: [A-Za-z0-9_-] only, with a short
    hash of the names whenever a character had to be replaced (two names never collide)."""
    raw = "_".join(str(p) for p in parts)
    slug = _NOT_ID.sub("_", raw)
    if slug != raw:
        slug += "_" + hashlib.sha256(raw.encode()).hexdigest()[:8]
    return slug


@dataclass(frozen=True, slots=True)
class Discovery:
    """Home Assistant MQTT discovery configs for one gateway's units and vehicles."""

    prefix: str  # mqtt.telemetry.discovery_prefix
    topics: Topics
    qos: int

    def _topic(self, uid: str) -> str:
        return f"{self.prefix}/sensor/{uid}/config"

    def _common(self, uid: str, state_topic: str, sensor: Sensor) -> dict[str, Any]:
        return {
            **sensor.config(),
            "unique_id": uid,
            "state_topic": state_topic,
            "availability_topic": self.topics.status,
            "payload_available": ONLINE,
            "payload_not_available": OFFLINE,
            "qos": self.qos,
            "origin": {"name": "eqgw", "sw_version": version()},
        }

    @staticmethod
    def vehicle_device(vehicle_id: str, name: str) -> dict[str, Any]:
        return {"identifiers": [object_id("eqgw", "vehicle", vehicle_id)], "name": name}

    def unit_configs(self, values: UnitValues, vehicle_name: str) -> list[tuple[str, bytes]]:
        """(topic, retained payload) of each sensor of the unit; an 80-series-only sensor of
        a 70-series unit gets an empty payload (which removes it), of a unit of unknown
        series nothing yet."""
        ref = UnitRef(values.vehicle_id, values.bus, values.sa)
        model = values.model or (f"VANN-Guard {values.series}-series" if values.series else None)
        device: dict[str, Any] = {
            "identifiers": [object_id("eqgw", "unit", ref.vehicle_id, ref.bus, ref.sa)],
            "name": f"{vehicle_name} equalizer {ref.sa}",
            "manufacturer": "Vanner",
            "via_device": self.vehicle_device(ref.vehicle_id, vehicle_name)["identifiers"][0],
        }
        if model is not None:
            device["model"] = model
        out: list[tuple[str, bytes]] = []
        for sensor in UNIT_SENSORS:
            uid = object_id("eqgw", ref.vehicle_id, ref.bus, ref.sa, sensor.key)
            if sensor.series_80 and values.series != 80:
                if values.series is not None:
                    out.append((self._topic(uid), b""))
                continue
            config = {**self._common(uid, self.topics.unit(ref), sensor), "device": device}
            out.append((self._topic(uid), orjson.dumps(config)))
        return out

    def vehicle_config(self, vehicle_id: str, name: str) -> tuple[str, bytes]:
        uid = object_id("eqgw", vehicle_id, "state")
        config = {
            **self._common(uid, self.topics.vehicle(vehicle_id), VEHICLE_SENSOR),
            "device": self.vehicle_device(vehicle_id, name),
        }
        return self._topic(uid), orjson.dumps(config)


# -- the publisher -------------------------------------------------------------------------------


@dataclass(slots=True)
class TelemetryCounters:
    """What the publisher did since it started (for /readyz and /metrics)."""

    changes: int = 0  # hub events that changed a unit or vehicle
    published: dict[str, int] = field(
        default_factory=lambda: {"unit": 0, "vehicle": 0, "discovery": 0}
    )
    deferred: int = 0  # rounds cut short by max_pending (their units waited)
    refused: int = 0  # publishes paho refused (not connected, its own queue full)
    resyncs: int = 0  # times the hub dropped the subscription (all republished)


class TelemetryPublisher:
    """Publishes the live state of the units this gateway reads (see the module docstring).

    `start` connects (paho's thread, with backoff), `run` is the supervised loop, `stop`
    says `offline` and disconnects, each bounded."""

    def __init__(
        self,
        settings: MqttSettings,
        gateway_id: str,
        hub: EventHub,
        live: LiveState,
        owned_buses: Callable[[], Iterable[str]],
        vehicle_names: Callable[[str], tuple[str, str | None]],
        *,
        not_reporting_after_s: float,
        queue: int = 10_000,
    ) -> None:
        self.settings = settings
        self.telemetry = settings.telemetry
        self.gateway_id = gateway_id
        self.topics = Topics(self.telemetry.topic_prefix, gateway_id)
        self.discovery = (
            Discovery(self.telemetry.discovery_prefix, self.topics, self.telemetry.qos)
            if self.telemetry.homeassistant
            else None
        )
        self.hub = hub
        self.live = live
        self.owned_buses = owned_buses
        self.vehicle_names = vehicle_names
        self.not_reporting_after_s = not_reporting_after_s
        self.queue = queue
        self.interval_s = self.telemetry.interval_s
        self.tick_s = min(TICK_S, self.interval_s / 2)
        self.counters = TelemetryCounters()
        # Set by paho's thread, read by the loop (plain attributes).
        self.connected = False
        self.last_error: str | None = None
        # Why it stopped connecting for good (the broker refused its credentials), else None.
        self.failed: str | None = None
        self.sessions = 0  # connections made so far (each said `online`)
        self.offline_said = 0  # clean stops that said `offline`
        self.reasserted = 0  # `offline` seen while connected, answered with `online`
        self._stopping = False
        self._client: paho.Client | None = None
        # The loop's own (event loop thread only).
        self._session_seen = 0
        self._owned: set[str] = set()
        self._dirty_units: dict[tuple[str, int], None] = {}
        self._dirty_vehicles: dict[str, None] = {}
        self._due_units: dict[tuple[str, int], float] = {}
        self._due_vehicles: dict[str, float] = {}
        self._vehicle_sent: dict[str, VehicleState] = {}
        self._unit_sent: dict[tuple[str, int], bytes] = {}
        self._swept = 0.0
        self._announced_units: dict[tuple[str, int], tuple[Any, ...]] = {}
        self._announced_vehicles: dict[str, str] = {}
        self._pending: list[paho.MQTTMessageInfo] = []
        self.collector = TelemetryCollector(self)

    # -- paho callbacks (its network thread: plain attributes and paho calls only) -----------

    def _on_connect(self, client: Any, _u: Any, _flags: Any, reason: Any, _props: Any) -> None:
        if reason.is_failure:
            self.connected = False
            self.last_error = f"connection refused: {reason}"
            if refused_for_good(reason):
                s = self.settings
                self.failed = give_up_connecting(client, "MQTT telemetry", s.host, s.port, reason)
                return
            log.warning("MQTT telemetry %s: %s", self.settings.host, reason)
            return
        client.publish(self.topics.status, ONLINE, qos=1, retain=True)
        # Its own status topic: an `offline` arriving while this gateway is connected (the
        # will of a connection of its own the broker dropped late, or of another process
        # with the same gateway id) is answered with `online` again.
        client.subscribe(self.topics.status, qos=1)
        self.sessions += 1
        self.connected = True
        self.last_error = None
        log.info("MQTT telemetry connected to %s:%s", self.settings.host, self.settings.port)

    def _on_message(self, client: Any, _u: Any, msg: Any) -> None:
        if msg.topic == self.topics.status and msg.payload == OFFLINE.encode():
            if self.connected and not self._stopping:
                client.publish(self.topics.status, ONLINE, qos=1, retain=True)
                self.reasserted += 1

    def _on_disconnect(self, _c: Any, _u: Any, _flags: Any, reason: Any, _props: Any) -> None:
        if self.connected and not self._stopping:
            log.warning("MQTT telemetry disconnected from %s: %s", self.settings.host, reason)
        self.connected = False
        self.last_error = f"disconnected: {reason}"

    def _on_connect_fail(self, _c: Any, _u: Any) -> None:
        self.connected = False
        self.last_error = "cannot connect"

    # -- lifecycle -----------------------------------------------------------------------------

    async def start(self) -> None:
        """Connect in the background (paho's thread retries with backoff)."""
        s = self.settings
        name = (
            f"{s.client_id}-telemetry" if s.client_id else f"eqgw-telemetry-{uuid.uuid4().hex[:12]}"
        )
        client = new_client(s, name)
        # The broker publishes this when the connection ends without a DISCONNECT: a killed
        # process, a lost link (after 1.5 keepalives without a packet).
        client.will_set(self.topics.status, OFFLINE, qos=1, retain=True)
        # paho's own bound on QoS 1 messages, above ours (a unit's discovery configs may
        # take a round past max_pending once).
        client.max_queued_messages_set(self.telemetry.max_pending + 100)
        client.on_connect = self._on_connect
        client.on_disconnect = self._on_disconnect
        client.on_connect_fail = self._on_connect_fail
        client.on_message = self._on_message
        client.connect_async(s.host or "", s.port, keepalive=s.keepalive_s)
        client.loop_start()
        self._client = client

    async def stop(self) -> None:
        """Say `offline` (the will is only for an unclean end) and disconnect, bounded."""
        client, self._client = self._client, None
        if client is None:
            return
        self._stopping = True
        if self.connected:
            info = client.publish(self.topics.status, OFFLINE, qos=1, retain=True)
            with contextlib.suppress(Exception):
                async with asyncio.timeout(STOP_PUBLISH_S + 0.5):
                    await asyncio.to_thread(info.wait_for_publish, STOP_PUBLISH_S)
            self.offline_said += 1
        client.disconnect()
        with contextlib.suppress(TimeoutError):
            async with asyncio.timeout(STOP_LOOP_S):
                await asyncio.to_thread(client.loop_stop)
        self.connected = False

    async def run(self) -> None:
        """The supervised loop: note the hub's changes, publish what is due, every tick."""
        sub = self._subscribe()
        try:
            while True:
                try:
                    self._drain(sub)
                except SubscriberLagged:
                    # More changes than the queue holds arrived between two rounds: start
                    # over from the live state (every unit again; nothing is lost).
                    self.counters.resyncs += 1
                    sub.close()
                    sub = self._subscribe()
                now = time.monotonic()
                if now - self._swept >= SWEEP_S:
                    self._swept = now
                    self._mark_all(keep_due=True)
                self.publish_round(now)
                await asyncio.sleep(self.tick_s)
        finally:
            sub.close()

    def _subscribe(self) -> Subscription:
        sub = self.hub.subscribe(UNIT_KINDS, maxsize=self.queue, predicate=_local)
        self._mark_all()
        return sub

    # -- the loop's work (event loop thread) ---------------------------------------------------

    def _drain(self, sub: Subscription) -> None:
        while (event := sub.get_nowait()) is not None:
            self.counters.changes += 1
            self._dirty_units[event.unit.key] = None
            self._dirty_vehicles[event.unit.vehicle_id] = None

    def _mark_all(self, *, keep_due: bool = False) -> None:
        """Every unit and vehicle read here looked at again (a new connection, a resync, the
        sweep); without `keep_due`, at once."""
        owned = self._owned
        for st in self.live.all_units():
            if st.ref.bus in owned:
                self._dirty_units[st.ref.key] = None
                self._dirty_vehicles[st.ref.vehicle_id] = None
        if not keep_due:
            self._due_units.clear()
            self._due_vehicles.clear()

    def _follow_ownership(self) -> None:
        """Buses taken: their units published now (discovery too). Buses given up: forgotten,
        so that taking one back announces it again (another gateway announced it since)."""
        owned = set(self.owned_buses())
        if owned == self._owned:
            return
        gone, new = self._owned - owned, owned - self._owned
        self._owned = owned
        for table in (self._announced_units, self._unit_sent):
            for key in [k for k in table if k[0] in gone]:
                del table[key]
        if gone:
            self._announced_vehicles.clear()
            self._vehicle_sent.clear()
        for st in self.live.all_units():
            if st.ref.bus in new:
                self._dirty_units[st.ref.key] = None
                self._due_units.pop(st.ref.key, None)
                self._dirty_vehicles[st.ref.vehicle_id] = None
                self._due_vehicles.pop(st.ref.vehicle_id, None)

    def _new_session(self) -> None:
        """A (re)connection: the broker may have lost everything retained; say it all again."""
        self._session_seen = self.sessions
        self._announced_units.clear()
        self._announced_vehicles.clear()
        self._vehicle_sent.clear()
        self._unit_sent.clear()
        self._pending.clear()  # paho dropped its QoS 0 packets; QoS 1 ones it resends itself
        self._mark_all()

    def _publish(self, topic: str, payload: bytes, qos: int, kind: str) -> bool:
        client = self._client
        if client is None:
            return False
        info = client.publish(topic, payload, qos=qos, retain=True)
        if info.rc != paho.MQTT_ERR_SUCCESS:
            self.counters.refused += 1
            return False
        self._pending.append(info)
        self.counters.published[kind] += 1
        return True

    def _room(self) -> bool:
        if len(self._pending) < self.telemetry.max_pending:
            return True
        self._pending = [i for i in self._pending if not i.is_published()]
        if len(self._pending) < self.telemetry.max_pending:
            return True
        self.counters.deferred += 1
        return False

    def publish_round(self, now: float) -> int:
        """Publish every dirty unit and vehicle that is due; returns the messages handed over."""
        self._follow_ownership()
        if self.sessions != self._session_seen:
            self._new_session()
        if not self.connected or self._client is None:
            return 0
        self._pending = [i for i in self._pending if not i.is_published()]
        sent = 0
        wall = time.time()
        for key in list(self._dirty_units):
            if self._due_units.get(key, 0.0) > now:
                continue
            st = self.live.get(*key)
            if st is None or key[0] not in self._owned:
                del self._dirty_units[key]
                continue
            if not self._room():
                return sent
            n = self._publish_unit(st, wall)
            if n is None:
                return sent
            sent += n
            del self._dirty_units[key]
            if n:
                self._due_units[key] = now + self.interval_s
        for vid in list(self._dirty_vehicles):
            if self._due_vehicles.get(vid, 0.0) > now:
                continue
            if not self._room():
                return sent
            n = self._publish_vehicle(vid, wall)
            if n is None:
                return sent
            sent += n
            del self._dirty_vehicles[vid]
            if n:
                self._due_vehicles[vid] = now + self.interval_s
        return sent

    def _publish_unit(self, st: UnitState, wall: float) -> int | None:
        """The unit's values (and its discovery configs when they changed); None when paho
        refused (it stays dirty)."""
        values = unit_values(st, self.gateway_id, wall)
        n = 0
        if self.discovery is not None:
            signature = (values.series, values.model, self.vehicle_names(values.vehicle_id)[0])
            if self._announced_units.get(st.ref.key) != signature:
                for topic, payload in self.discovery.unit_configs(values, signature[2]):
                    if not self._publish(topic, payload, 1, "discovery"):
                        return None
                    n += 1
                self._announced_units[st.ref.key] = signature
        payload = orjson.dumps(values)
        if self._unit_sent.get(st.ref.key) == payload:
            return n
        if not self._publish(self.topics.unit(st.ref), payload, self.telemetry.qos, "unit"):
            return None
        self._unit_sent[st.ref.key] = payload
        return n + 1

    def _publish_vehicle(self, vehicle_id: str, wall: float) -> int | None:
        """The vehicle's state if this gateway reads its lead unit and it changed (0 when
        there is nothing to say); None when paho refused."""
        units = self.live.of_vehicle(vehicle_id)
        status = vehicle_status(units, wall, self.not_reporting_after_s)
        if status.lead is None or status.lead[0] not in self._owned:
            return 0
        name, depot = self.vehicle_names(vehicle_id)
        state = VehicleState(
            vehicle_id, name, depot, status.state, status.parked_since, self.gateway_id
        )
        n = 0
        if self.discovery is not None and self._announced_vehicles.get(vehicle_id) != name:
            topic, payload = self.discovery.vehicle_config(vehicle_id, name)
            if not self._publish(topic, payload, 1, "discovery"):
                return None
            self._announced_vehicles[vehicle_id] = name
            n += 1
        if self._vehicle_sent.get(vehicle_id) == state:
            return n
        if not self._publish(
            self.topics.vehicle(vehicle_id), orjson.dumps(state), self.telemetry.qos, "vehicle"
        ):
            return None
        self._vehicle_sent[vehicle_id] = state
        return n + 1

    # -- reporting -----------------------------------------------------------------------------

    def published(self) -> dict[str, int]:
        """Messages handed to the connection, by kind."""
        said = self.sessions + self.reasserted + self.offline_said
        return {**self.counters.published, "status": said}

    def status(self) -> dict[str, Any]:
        """For /readyz (reported only: telemetry never makes a gateway unready)."""
        return {
            "connected": self.connected,
            "last_error": self.last_error,
            "failed": self.failed,
            "gateway_id": self.gateway_id,
            "status_topic": self.topics.status,
            "units_waiting": len(self._dirty_units),
            "pending": len(self._pending),
            "published": self.published(),
            "changes": self.counters.changes,
            "deferred": self.counters.deferred,
            "resyncs": self.counters.resyncs,
        }


def _local(event: Event) -> bool:
    """Changes of units this gateway reads (another gateway publishes its own)."""
    return not is_remote(event)


class TelemetryCollector(Collector):
    """The telemetry's counters for Prometheus, read at scrape time."""

    def __init__(self, publisher: TelemetryPublisher) -> None:
        self.publisher = publisher

    def collect(self) -> Iterator[Metric]:
        p = self.publisher
        c = p.counters
        yield GaugeMetricFamily(
            "eqgw_mqtt_telemetry_connected",
            "1 while the telemetry is connected to the broker",
            value=1.0 if p.connected else 0.0,
        )
        yield GaugeMetricFamily(
            "eqgw_mqtt_telemetry_failed",
            "1 once the broker refused the telemetry's credentials (not retried; see /readyz)",
            value=1.0 if p.failed else 0.0,
        )
        published = CounterMetricFamily(
            "eqgw_mqtt_telemetry_published",
            "Telemetry messages handed to the broker's connection, by kind (unit, vehicle, "
            "discovery, status)",
            labels=["kind"],
        )
        for kind, n in sorted(p.published().items()):
            published.add_metric([kind], n)
        yield published
        yield CounterMetricFamily(
            "eqgw_mqtt_telemetry_changes",
            "Live changes of the units read here (each coalesced into its unit's next publish)",
            value=c.changes,
        )
        yield CounterMetricFamily(
            "eqgw_mqtt_telemetry_deferred",
            "Publish rounds cut short by mqtt.telemetry.max_pending (the rest waited)",
            value=c.deferred,
        )
        yield CounterMetricFamily(
            "eqgw_mqtt_telemetry_refused",
            "Publishes the MQTT client refused (not connected, its queue full); retried",
            value=c.refused,
        )
        yield CounterMetricFamily(
            "eqgw_mqtt_telemetry_resyncs",
            "Times the telemetry fell a whole hub queue behind and republished every unit",
            value=c.resyncs,
        )
        yield GaugeMetricFamily(
            "eqgw_mqtt_telemetry_pending",
            "Telemetry messages not yet written (QoS 0) or acknowledged (QoS 1)",
            value=len(p._pending),
        )
