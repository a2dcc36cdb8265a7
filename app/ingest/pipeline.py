"""The ingest pipeline: frames -> decode -> per-unit state and faults -> writer rows and events."""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field

from eqgw.config import MonitorSettings, Settings
from eqgw.ingest import events
from eqgw.ingest.events import Event, UnitRef
from eqgw.ingest.faults import BusActivity, Change, FaultTracker
from eqgw.ingest.hub import EventHub
from eqgw.ingest.rows import (
    BatteryStateRow,
    Dm1SnapshotRow,
    EpisodeRow,
    LiveRow,
    MeasurementRow,
    MessageRow,
    RawFrameRow,
    Row,
    SeenRow,
    StatusChangeRow,
    UnitInfoRow,
    UnitOwnerRow,
    UnitRow,
    VehicleRow,
)
from eqgw.ingest.state import CLAIM_SLOT, LiveState, UnitState, live_key, vehicle_status
from eqgw.jsontypes import JSONObject, JSONValue, as_int
from eqgw.protocol.claims import PGN_ADDRESS_CLAIMED, ClaimTracker, OwnerChange
from eqgw.protocol.decode import LOOKALIKE_PGNS, FrameDecoder, FrameLike
from eqgw.protocol.j1939 import (
    GLOBAL_ADDRESS,
    PGN_CONTROL,
    PGN_PARAMETERS,
    PGN_REQUEST,
    PGN_TP_CM,
)
from eqgw.protocol.records import Record
from eqgw.store.queries import RestartUnitRow
from eqgw.store.writes import (
    BatteryValues,
    MeasurementValues,
    UnitInfo,
    UnitKey,
    VehicleInfo,
)

log = logging.getLogger(__name__)

# A message's handler in `IngestPipeline._apply`: (unit, record, from the unit itself,
# fault changes to add to).
_Handler = Callable[[UnitState, Record, bool, list[Change]], None]

_TO_EQUALIZER = frozenset({"control", "parameters", "request"})
_IDENTIFICATION = frozenset({"component_id", "software_id"})
# How often (in frame time) live state and last-seen times are handed to the writer.
# Monitors run every second; the in-memory view is always current, the database copy of the
# live state follows every few seconds (it only serves restarts).
TICK_EVERY_S = 1.0
PERSIST_EVERY_S = 5.0
# Bound of each bus's set of other nodes' frame ids (a bus has a few hundred).
_SKIP_IDS_LIMIT = 65536


@dataclass(slots=True)
class BusBinding:
    """One bus as the pipeline sees it: name, vehicle, equalizer addresses, its decoder."""

    bus: str
    vehicle_id: str
    equalizer_sas: tuple[int, ...] = (0x1E,)
    request_byte_order: str = "lsb"
    decoder: FrameDecoder = field(init=False)
    sas: frozenset[int] = field(init=False)
    skip_ids: set[int] = field(init=False)  # ids of frames the decoder never needs
    claims: ClaimTracker = field(init=False)  # who holds which address (PGN 60928)
    # Units were restored onto this bus and it has not been seen open since (`bus_opened`).
    awaiting_open: bool = field(default=False, init=False)
    # Every node's frames on the bus: silent units are parked, not offline, with a silent bus.
    activity: BusActivity = field(default_factory=BusActivity)

    def __post_init__(self) -> None:
        self.sas = frozenset(self.equalizer_sas)
        self.skip_ids = set()
        self.claims = ClaimTracker()
        self.decoder = FrameDecoder(self.equalizer_sas, request_byte_order=self.request_byte_order)


@dataclass(slots=True)
class PipelineStats:
    """Counters of the pipeline (frames it was given, records, rows, unmapped channels)."""

    frames: int = 0
    skipped_frames: int = 0  # other nodes' traffic, never handed to the decoder
    records: int = 0
    rows: int = 0
    unmapped_frames: int = 0
    archived_frames: int = 0
    # Records to the equalizers (control, parameters, requests) on a bus with no unit heard:
    # another vendor's use of the same proprietary PGNs, or a unit not heard yet; not stored.
    to_no_unit: int = 0


class IngestPipeline:
    """Turns frames into rows for the writer and events for the hub; synchronous and pure CPU.

    Frames are routed to a bus by `msg.channel` (the bus name for live buses, the mapped log
    channel for replays). Rows accumulate in memory until the runner calls `take_rows()`.
    """

    def __init__(
        self,
        bindings: Iterable[BusBinding],
        *,
        channel_map: dict[str | None, str] | None = None,
        vehicles: dict[str, VehicleInfo] | None = None,
        hub: EventHub | None = None,
        monitor: MonitorSettings | None = None,
        raw_archive: bool = True,
    ) -> None:
        self.bindings = {b.bus: b for b in bindings}
        # Log channel (as str, or None) -> bus name; live buses route by their own name.
        self._route: dict[object, BusBinding] = {}
        for channel, bus in (channel_map or {}).items():
            self._route[channel] = self.bindings[bus]
        for name, b in self.bindings.items():
            self._route.setdefault(name, b)
        # Frames of channels nobody mapped: a replay's `--vehicle ID` (key None) takes them all;
        # with explicit per-channel maps they are counted as unmapped, not guessed.
        if channel_map is not None:
            self._default = self._route.get(None)
        else:
            self._default = next(iter(self.bindings.values())) if len(self.bindings) == 1 else None
        self.vehicles = vehicles or {}
        self.hub = hub or EventHub()
        self.monitor = monitor or MonitorSettings()
        self.raw_archive = raw_archive
        self.live = LiveState()
        # Buses whose units are monitored and persisted from here; None: all. With several
        # gateways on one database, units of buses another gateway reads are only mirrored.
        self.active: set[str] | None = None
        self.stats = PipelineStats()
        self.clock = float("-inf")
        self._last_tick = float("-inf")
        self._last_persist = float("-inf")
        self._rows: list[Row] = []
        # Live state and last-seen spans wait here until handed over, one row per key: a
        # replay persists every few seconds of log time, and only the latest counts.
        self._live_rows: dict[tuple[UnitKey, str], tuple[float, JSONObject]] = {}
        self._seen_rows: dict[UnitKey, list[float]] = {}
        # Per unit, the timestamp of its latest archived frame and how many frames of each id
        # carried it: several frames of one id can share a timestamp (a log's resolution,
        # multi-frame records), and each is archived under its own index within that group.
        self._raw_groups: dict[UnitKey, tuple[float, dict[int, int]]] = {}
        self._vehicles_sent: set[str] = set()
        self._vehicle_states: dict[str, str] = {}  # the state last published per vehicle
        # `_apply`: each message its handler; every other one is kept as a message.
        self._handlers: dict[str, _Handler] = {
            "voltages": self._on_voltages,
            "battery_states": self._on_battery_states,
            "status": self._on_status,
            "heartbeat": self._on_heartbeat,
            "dm1": self._on_dm1,
        }
        for b in self.bindings.values():
            b.activity.silent_after_s = self.monitor.bus_silent_after_s

    @classmethod
    def from_settings(cls, settings: Settings, hub: EventHub | None = None) -> IngestPipeline:
        """A pipeline for the live buses of the configuration."""
        bindings = [
            BusBinding(b.name, b.vehicle_id, tuple(b.equalizer_sas), b.request_byte_order)
            for b in settings.buses
        ]
        vehicles: dict[str, VehicleInfo] = {
            v.id: {"id": v.id, "name": v.display_name, "depot": v.depot} for v in settings.vehicles
        }
        return cls(
            bindings,
            vehicles=vehicles,
            hub=hub,
            monitor=settings.monitor,
            raw_archive=settings.raw_archive,
        )

    # -- the hot path --------------------------------------------------------------------

    def _binding(self, channel: object) -> BusBinding | None:
        b = self._route.get(channel)
        if b is None:
            b = self._route.get(None if channel is None else str(channel), self._default)
            if b is not None:
                self._route[channel] = b
        return b

    def process(self, msg: FrameLike) -> None:
        """Consume one `can.Message` (live or replayed)."""
        self.process_many((msg,))

    def process_many(self, msgs: Iterable[FrameLike]) -> None:
        """Consume `can.Message`s in order; the loop the replay and the live readers run."""
        stats = self.stats
        route = self._route
        frames = skipped = 0
        clock = self.clock
        last_tick = self._last_tick
        try:
            for msg in msgs:
                frames += 1
                b = route.get(msg.channel) or self._binding(msg.channel)
                if b is None:
                    stats.unmapped_frames += 1
                    continue
                ts = msg.timestamp
                if b.awaiting_open:
                    self.bus_opened(b.bus, ts)
                # Any node's frame is traffic on the bus (BusActivity.on_frame, inlined).
                act = b.activity
                if ts > act.heard:
                    if ts - act.heard > act.silent_after_s:
                        act.active_since = ts
                    act.heard = ts
                if ts > clock:
                    clock = self.clock = ts
                    if ts - last_tick >= TICK_EVERY_S:
                        self.tick(ts)
                        last_tick = self._last_tick
                can_id = msg.arbitration_id
                # Most of a vehicle bus is other nodes' traffic: one set lookup drops it.
                if can_id in b.skip_ids:
                    skipped += 1
                    continue
                if self._skippable(b, can_id):
                    skipped += 1
                    continue
                data = bytes(msg.data)
                ext, remote, error = msg.is_extended_id, msg.is_remote_frame, msg.is_error_frame
                records = b.decoder.decode(
                    ts, b.bus, can_id, data, is_extended=ext, is_remote=remote, is_error=error
                )
                if self.raw_archive and ext and not remote and not error:
                    self._archive(b, ts, can_id, data, bool(records))
                for rec in records:
                    self._handle(b, rec)
                if (can_id >> 16) & 0xFF == 0xEE and ext:  # an address claim (PGN 60928)
                    for change in b.claims.observe(ts, can_id, data):
                        self._owner_change(b, change)
        finally:
            stats.frames += frames
            stats.skipped_frames += skipped

    @staticmethod
    def _skippable(b: BusBinding, can_id: int) -> bool:
        """Whether a frame id is neither from an equalizer nor a command or request that may
        be for one (remembered in `b.skip_ids`, so the next frame costs one lookup)."""
        if (can_id & 0xFF) in b.sas:
            return False
        pgn = (can_id >> 8) & 0x3FFFF
        if pgn == PGN_CONTROL or pgn == PGN_PARAMETERS or (pgn & 0x3FF00) == PGN_REQUEST:
            return False
        if (pgn & 0x3FF00) == PGN_TP_CM:
            return False  # other nodes' transport sessions: their DM1s are counted
        if (pgn & 0x3FF00) == PGN_ADDRESS_CLAIMED:
            return False  # address claims: who holds the equalizers' addresses
        if pgn in LOOKALIKE_PGNS:
            return False  # counted by address by the decoder (an equalizer nobody named?)
        if len(b.skip_ids) < _SKIP_IDS_LIMIT:
            b.skip_ids.add(can_id)
        return True

    def _archive(self, b: BusBinding, ts: float, can_id: int, data: bytes, decoded: bool) -> None:
        sa = can_id & 0xFF
        if sa not in b.equalizer_sas:
            pf = (can_id >> 16) & 0xFF
            pgn = (can_id >> 8) & (0x3FF00 if pf < 240 else 0x3FFFF)
            if pgn == PGN_REQUEST:
                da = (can_id >> 8) & 0xFF
                if da in b.equalizer_sas:
                    sa = da
                elif da == GLOBAL_ADDRESS and decoded:
                    # A request to all is the equalizers' only when it asks for what they
                    # answer (then it is a request record); other nodes' are not archived.
                    sa = self._first_known(b)
                else:
                    return
            elif pgn in (PGN_CONTROL, PGN_PARAMETERS):
                sa = self._first_known(b)  # broadcast to the bus's equalizers
            else:
                return
            if (b.bus, sa) not in self.live.units:
                # Traffic to the equalizers never creates a unit: with none heard on the bus
                # it is another vendor's (or waits for nobody), like the records it carries.
                return
        key = self._unit(b, sa, ts).ref.key
        group = self._raw_groups.get(key)
        if group is None or group[0] != ts:
            group = self._raw_groups[key] = (ts, {})
        seq = group[1][can_id] = group[1].get(can_id, -1) + 1
        self._rows.append(RawFrameRow(key, {"ts": ts, "can_id": can_id, "seq": seq, "data": data}))
        self.stats.archived_frames += 1

    def continue_groups(self, groups: Mapping[UnitKey, tuple[float, dict[int, int]]]) -> None:
        """Continue the archive's groups of frames sharing a timestamp from what is stored
        (`eqgw.store.archive.last_groups`): per unit, the newest timestamp and per identifier
        the last index used at it."""
        for key, (ts, seqs) in groups.items():
            self._raw_groups[key] = (ts, dict(seqs))

    def _first_known(self, b: BusBinding) -> int:
        """The first of a bus's equalizer addresses with a unit heard (else the first)."""
        units = self.live.units
        return next((sa for sa in b.equalizer_sas if (b.bus, sa) in units), b.equalizer_sas[0])

    def restore(self, units: Iterable[RestartUnitRow]) -> int:
        """Take back persisted state at start (rows of `eqgw.store.queries.restart_state`):
        live values show at once and open episodes continue. Units of buses this pipeline
        does not read are left out. Returns the units restored."""
        n = 0
        series: dict[str, dict[tuple[str | None, int], int]] = {}
        for unit in map(RestartUnit.of, units):
            b = self.bindings.get(unit.bus)
            if b is None or (b.bus, unit.sa) in self.live.units:
                continue
            st = self._new_unit(b, unit.sa)
            st.series, st.model, st.software_id = unit.series, unit.model, unit.software_id
            st.first_seen, st.last_seen = unit.first_seen, unit.last_seen
            live = unit.live
            claim = live.get(CLAIM_SLOT)
            if claim is not None and claim[1].get("owner_changed"):
                # Slots older than a change of owner were the previous node's.
                live = {slot: v for slot, v in live.items() if v[0] >= claim[0]}
            st.latest.update(live)
            if "status" in live:
                st.status_flags = live["status"][1]
            if "dm1" in live:
                dm1 = live["dm1"][1]
                st.dm1 = (dm1.get("lamps"), dm1.get("dtcs"))
            heartbeat = as_int(live.get("heartbeat", (0.0, {}))[1].get("heartbeat"))
            st.faults.restore(unit.episodes, st.last_seen, heartbeat)
            b.awaiting_open = True
            if st.series:
                series.setdefault(b.bus, {})[(b.bus, unit.sa)] = st.series
            n += 1
        # Decoders learn a unit's series from its identification; a restart starts knowing it.
        for bus, known in series.items():
            b = self.bindings[bus]
            b.decoder = FrameDecoder(
                b.equalizer_sas, request_byte_order=b.request_byte_order, series=known
            )
        return n

    def bus_opened(self, bus: str, ts: float) -> None:
        """A bus is open (its first frame, or its reader's word) at `ts`: units restored onto
        it count as silent from then on, not from their last frame before a restart."""
        b = self.bindings.get(bus)
        if b is None or not b.awaiting_open:
            return
        b.awaiting_open = False
        for st in self.live.units.values():
            if st.ref.bus == bus:
                st.faults.on_bus_open(ts)

    def _new_unit(self, b: BusBinding, sa: int) -> UnitState:
        m = self.monitor
        st = UnitState(
            ref=UnitRef(b.vehicle_id, b.bus, sa),
            faults=FaultTracker(
                offline_after_s=m.offline_after_s,
                dm1_stale_after_s=m.dm1_stale_after_s,
                heartbeat_stuck_after=m.heartbeat_stuck_after,
            ),
        )
        self.live.units[(b.bus, sa)] = st
        return st

    def _unit(self, b: BusBinding, sa: int, ts: float) -> UnitState:
        key = (b.bus, sa)
        st = self.live.units.get(key)
        if st is not None:
            return st
        vid = b.vehicle_id
        if vid not in self._vehicles_sent:
            self._vehicles_sent.add(vid)
            info = self.vehicles.get(vid) or {"id": vid, "name": vid, "depot": None}
            self._rows.append(VehicleRow(vid, info))
        st = self._new_unit(b, sa)
        self._rows.append(UnitRow(key, vid))
        if self.hub.wants(events.UNIT_ONLINE):
            self.hub.publish(Event(events.UNIT_ONLINE, st.ref, ts))
        return st

    def _owner_change(self, b: BusBinding, change: OwnerChange) -> None:
        """An address claim decided who holds an address: for an equalizer's, the unit is its
        NAME. When another NAME takes it, the old node's unit ends (its open episodes close,
        its live state is kept in the database, its learned series is forgotten) and the new
        owner's frames start a new one; the claim is recorded on the unit either way."""
        sa = change.address
        if sa not in b.sas:
            return
        key = (b.bus, sa)
        st = self.live.units.get(key)
        previous = change.previous
        if previous is None and st is not None and CLAIM_SLOT in st.latest:
            # Known from before a restart (or a bus reopening): compare with that NAME.
            previous = int(str(st.latest[CLAIM_SLOT][1]["name"]), 16)
        replaced = previous is not None and previous != change.name
        if replaced and st is not None:
            log.warning(
                "bus %s: address %d is now held by NAME 0x%016X, not 0x%016X: the unit's "
                "data so far ends, later frames are the new node's",
                b.bus,
                sa,
                change.name,
                previous,
            )
            ended = st.faults.end_all(change.ts, "address_lost")
            if ended:
                self._fault_changes(st, ended)
            self._persist(st)
            del self.live.units[key]
            b.decoder.forget(b.bus, sa)
        name = f"0x{change.name:016X}"
        fields: JSONObject = {
            "name": name,
            "previous_name": None if previous is None else f"0x{previous:016X}",
            "owner_changed": replaced,
        }
        rec = Record(change.ts, b.bus, sa, PGN_ADDRESS_CLAIMED, CLAIM_SLOT, fields)
        unit = self._unit(b, sa, change.ts)
        if replaced or previous is None:
            # The unit row takes the NAME (and drops the previous node's identity) and a
            # period of ownership starts.
            self._rows.append(UnitOwnerRow(key, change.ts, name))
        self._apply(unit, rec, from_unit=False)

    def _handle(self, b: BusBinding, rec: Record) -> None:
        self.stats.records += 1
        if rec.name in _TO_EQUALIZER:
            # Traffic to the equalizers (a proprietary PGN another vendor may use too): it is
            # kept against the units already known on the bus and never creates one.
            da = rec.fields.get("da")
            targets: Iterable[int] = (
                (da,)
                if rec.name == "request" and isinstance(da, int) and da in b.equalizer_sas
                else b.equalizer_sas
            )
            units = self.live.units
            known = [st for sa in targets if (st := units.get((b.bus, sa))) is not None]
            if not known:
                self.stats.to_no_unit += 1
            for st in known:
                self._apply(st, rec, from_unit=False)
        else:
            self._apply(self._unit(b, rec.sa, rec.ts), rec, from_unit=True)

    def _apply(self, st: UnitState, rec: Record, *, from_unit: bool) -> None:
        """One record into its unit's state: rows, live slot, events, fault changes. Each
        message has its handler (`self._handlers`); every other message is kept as is."""
        changes = self._heard(st, rec.ts) if from_unit else []
        self._handlers.get(rec.name, self._on_message)(st, rec, from_unit, changes)
        ts, f = rec.ts, rec.fields
        hub = self.hub
        slot = live_key(rec.name, f)
        prev_live = st.latest.get(slot)
        if prev_live is None or prev_live[0] <= ts:
            st.latest[slot] = (ts, f)
            st.dirty.add(slot)
            if hub.wants(events.LIVE) and (prev_live is None or prev_live[1] != f):
                hub.publish(Event(events.LIVE, st.ref, ts, {"slot": slot, "fields": f}))
        if hub.wants(events.RECORD):
            hub.publish(Event(events.RECORD, st.ref, ts, rec.to_dict()))
        if changes:
            self._fault_changes(st, changes)

    def _heard(self, st: UnitState, ts: float) -> list[Change]:
        """A frame from the unit itself: it is back if parked, its seen span and first and
        last frame times widen, its silence monitor restarts."""
        parked = st.faults.parked_since
        if parked is not None and self.hub.wants(events.UNIT_ONLINE):
            self.hub.publish(Event(events.UNIT_ONLINE, st.ref, ts, {"parked_since": parked}))
        seen = st.seen_since_flush
        if seen is None:
            st.seen_since_flush = [ts, ts]
        elif ts > seen[1]:
            seen[1] = ts
        elif ts < seen[0]:
            seen[0] = ts
        if st.first_seen is None or ts < st.first_seen:
            st.first_seen = ts
        if st.last_seen is None or ts > st.last_seen:
            st.last_seen = ts
        return st.faults.on_frame(ts)

    # -- one handler per message (`_apply`); `changes` collects the fault changes ---------

    def _on_voltages(
        self, st: UnitState, rec: Record, from_unit: bool, changes: list[Change]
    ) -> None:
        f = rec.fields
        values: MeasurementValues = {
            "ts": rec.ts,
            "v12": f["v12"],
            "v24": f["v24"],
            "i12": f["i12"],
            "i24": f["i24"],
        }
        self._rows.append(MeasurementRow(st.ref.key, values))

    def _on_battery_states(
        self, st: UnitState, rec: Record, from_unit: bool, changes: list[Change]
    ) -> None:
        self._rows.append(BatteryStateRow(st.ref.key, _battery_row(rec.ts, rec.fields)))

    def _on_status(
        self, st: UnitState, rec: Record, from_unit: bool, changes: list[Change]
    ) -> None:
        ts, f = rec.ts, rec.fields
        prev = st.status_flags
        if prev != f:
            changed = [k for k, v in f.items() if prev is None or prev.get(k) != v]
            self._rows.append(
                StatusChangeRow(st.ref.key, {"ts": ts, "flags": f, "changed": changed})
            )
            if self.hub.wants(events.STATUS_CHANGE):
                data: JSONObject = {"flags": f, "changed": [*changed]}
                self.hub.publish(Event(events.STATUS_CHANGE, st.ref, ts, data))
            st.status_flags = f
        changes.extend(st.faults.on_status(ts, f))

    def _on_heartbeat(
        self, st: UnitState, rec: Record, from_unit: bool, changes: list[Change]
    ) -> None:
        value = rec.fields.get("heartbeat")  # an int 0..3, as decoded (None: not available)
        changes.extend(st.faults.on_heartbeat(rec.ts, value if isinstance(value, int) else None))

    def _on_dm1(self, st: UnitState, rec: Record, from_unit: bool, changes: list[Change]) -> None:
        ts, f = rec.ts, rec.fields
        content = (f.get("lamps"), f.get("dtcs"))
        if content != st.dm1:
            self._rows.append(
                Dm1SnapshotRow(st.ref.key, {"ts": ts, "lamps": content[0], "dtcs": content[1]})
            )
            st.dm1 = content
        changes.extend(st.faults.on_dm1(ts, f))

    def _on_message(
        self, st: UnitState, rec: Record, from_unit: bool, changes: list[Change]
    ) -> None:
        """Every other message (identification, control, parameters, requests, address
        claims) is kept in `messages`; a unit's own identification also on its row."""
        ts, name, f = rec.ts, rec.name, rec.fields
        key = st.ref.key
        idx = f.get("index") if name == "parameters" else 0
        self._rows.append(MessageRow(key, {"ts": ts, "name": name, "idx": idx or 0, "fields": f}))
        if name in _IDENTIFICATION and from_unit:
            series = f.get("series")
            info: UnitInfo = {"ts": ts, "series": series}
            text = f.get("text")
            if name == "component_id":
                info["model"] = text
                st.model = _text(text)
            else:
                info["software_id"] = text
                st.software_id = _text(text)
            if series:
                st.series = _series(series)
            self._rows.append(UnitInfoRow(key, info))

    def _fault_changes(self, st: UnitState, changes: list[Change]) -> None:
        key = st.ref.key
        for kind, ep in changes:
            row = ep.row()
            self._rows.append(EpisodeRow((key, ep.fault, ep.started_at), row))
            if self.hub.wants(kind):
                self.hub.publish(Event(kind, st.ref, ep.last_seen_at, ep.to_dict()))

    # -- clock and hand-over ---------------------------------------------------------------

    def tick(self, now: float) -> None:
        """Advance the monitors to `now`; every PERSIST_EVERY_S queue live state and last seen."""
        self._last_tick = now
        for binding in self.bindings.values():  # address challenges nobody defended
            for change in binding.claims.tick(now):
                self._owner_change(binding, change)
        persist = now - self._last_persist >= PERSIST_EVERY_S
        if persist:
            self._last_persist = now
        active = self.active
        bindings = self.bindings
        hub = self.hub
        for st in self.live.units.values():
            if active is not None and st.ref.bus not in active:
                continue
            b = bindings.get(st.ref.bus)
            parked = st.faults.parked_since
            changes = st.faults.tick(now, b.activity if b is not None else None)
            if changes:
                self._fault_changes(st, changes)
            if (
                st.faults.parked_since is not None
                and parked is None
                and hub.wants(events.UNIT_PARKED)
            ):
                data: JSONObject = {
                    "parked_since": st.faults.parked_since,
                    "last_seen": st.last_seen,
                }
                hub.publish(Event(events.UNIT_PARKED, st.ref, now, data))
            if persist:
                self._persist(st)
        if hub.wants(events.VEHICLE_STATE):
            self._vehicle_state_changes(now)

    def _vehicle_state_changes(self, now: float) -> None:
        """Publish each vehicle whose state moved since the last tick (not its first)."""
        active = self.active
        after = self.monitor.not_reporting_after_s
        known = self._vehicle_states
        for vid, table in self.live.units.by_vehicle.items():
            units = [u for u in table.values() if active is None or u.ref.bus in active]
            if not units:
                continue
            status = vehicle_status(units, now, after)
            before = known.get(vid)
            known[vid] = status.state
            if before is not None and before != status.state and status.lead is not None:
                lead = table[status.lead].ref
                self.hub.publish(Event(events.VEHICLE_STATE, lead, now, status.to_dict()))

    def _persist(self, st: UnitState) -> None:
        key = st.ref.key
        seen = st.seen_since_flush
        if seen is not None:
            pending = self._seen_rows.get(key)
            if pending is None:
                self._seen_rows[key] = seen
            else:
                pending[0] = min(pending[0], seen[0])
                pending[1] = max(pending[1], seen[1])
            st.seen_since_flush = None
        if st.dirty:
            live = self._live_rows
            latest = st.latest
            for slot in st.dirty:
                live[(key, slot)] = latest[slot]  # the latest is never older than what waits
            st.dirty.clear()

    def take_rows(self) -> list[Row]:
        """The rows produced since the last call (the runner hands them to the writer)."""
        rows, self._rows = self._rows, []
        if self._seen_rows:
            rows.extend(SeenRow(key, span[0], span[1]) for key, span in self._seen_rows.items())
            self._seen_rows = {}
        if self._live_rows:
            rows.extend(
                LiveRow(key, {"ts": ts, "fields": fields})
                for key, (ts, fields) in self._live_rows.items()
            )
            self._live_rows = {}
        self.stats.rows += len(rows)
        return rows

    def finish(self) -> None:
        """End of input: complete the decoders and queue the last live state (no monitors:
        the end of a log is not a unit going silent)."""
        for b in self.bindings.values():
            b.decoder.finish()
        for st in self.live.units.values():
            if self.active is None or st.ref.bus in self.active:
                self._persist(st)

    def persist_bus(self, bus: str) -> None:
        """Queue the live state of one bus's units now (before another gateway reads it)."""
        for st in self.live.units.values():
            if st.ref.bus == bus:
                self._persist(st)

    def register_units(self, bus: str) -> None:
        """Queue the unit rows of one bus's units, so the writer knows their ids: units
        restored from the database may have been registered by another gateway."""
        for st in self.live.units.values():
            if st.ref.bus == bus:
                self._rows.append(UnitRow(st.ref.key, st.ref.vehicle_id))

    def add_binding(self, binding: BusBinding) -> None:
        """Take a bus added to the fleet while running (its frames route by its name)."""
        binding.activity.silent_after_s = self.monitor.bus_silent_after_s
        self.bindings[binding.bus] = binding
        self._route[binding.bus] = binding

    def remove_binding(self, bus: str) -> None:
        """Forget a bus taken out of the fleet: its units leave the live view, its frames
        (late ones of a reader stopping) are unmapped from now on."""
        self.reset_bus(bus)
        b = self.bindings.pop(bus, None)
        if b is None:
            return
        for channel in [c for c, routed in self._route.items() if routed is b]:
            del self._route[channel]
        if self._default is b:
            self._default = None
        if self.active is not None:
            self.active.discard(bus)

    def reset_bus(self, bus: str) -> None:
        """Forget one bus's units and decoder state, before its state is restored afresh."""
        for key in [k for k in self.live.units if k[0] == bus]:
            del self.live.units[key]
        b = self.bindings.get(bus)
        if b is not None:
            b.decoder = FrameDecoder(b.equalizer_sas, request_byte_order=b.request_byte_order)
            b.skip_ids.clear()
            b.activity = BusActivity(self.monitor.bus_silent_after_s)

    @property
    def pending_rows(self) -> int:
        return len(self._rows) + len(self._live_rows) + len(self._seen_rows)


@dataclass(frozen=True, slots=True)
class RestartUnit:
    """A unit as a restarting gateway takes it back: a row of
    `eqgw.store.queries.restart_state`, its live slots (name -> (ts, fields)) and its open
    episodes (rows of `fault_episodes`)."""

    bus: str
    sa: int
    series: int | None
    model: str | None
    software_id: str | None
    first_seen: float | None
    last_seen: float | None
    live: dict[str, tuple[float, JSONObject]]
    episodes: list[Mapping[str, object]]

    @classmethod
    def of(cls, row: RestartUnitRow) -> RestartUnit:
        return cls(
            bus=row["bus"],
            sa=row["sa"],
            series=row["series"],
            model=row["model"],
            software_id=row["software_id"],
            first_seen=row["first_seen"],
            last_seen=row["last_seen"],
            live=dict(row["live"]),
            episodes=[*row["episodes"]],
        )


def _text(value: JSONValue) -> str | None:
    """An identification's text (a string, as decoded; None if absent)."""
    return value if isinstance(value, str) else None


def _series(value: JSONValue) -> int | None:
    """An identification's series (70 or 80, as decoded)."""
    return value if isinstance(value, int) else None


def _battery_row(ts: float, f: JSONObject) -> BatteryValues:
    return {
        "ts": ts,
        "idx": f.get("index"),
        "battery": f.get("battery"),
        "soc": f.get("soc"),
        "soc_achievable": f.get("soc_achievable"),
        "soh": f.get("soh"),
        "dod": f.get("dod"),
        "runtime_min": f.get("runtime_min"),
        "runtime_temp_adj_min": f.get("runtime_temp_adj_min"),
        "major_12v": f.get("major_12v"),
        "minor_12v": f.get("minor_12v"),
        "major_24v": f.get("major_24v"),
        "minor_24v": f.get("minor_24v"),
        "temperature_c": f.get("temperature_c"),
        "temperature_raw": f.get("temperature_raw"),
    }
