"""Per-unit live state kept in memory: latest values, status flags, DM1, open fault episodes."""

from __future__ import annotations

import time
from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import TypeVar, overload

from eqgw.ingest.events import UnitRef
from eqgw.ingest.faults import OFFLINE, FaultTracker
from eqgw.jsontypes import JSONObject, JSONValue


def live_key(name: str, fields: JSONObject) -> str:
    """The live-state slot of a record: multiplexed messages keep one slot per index."""
    if name in ("battery_states", "parameters"):
        return f"{name}/{fields.get('index')}"
    return name


# The live slot (and message name) of a unit's J1939 address claim: its NAME.
CLAIM_SLOT = "address_claim"

_T = TypeVar("_T")


@dataclass(slots=True)
class UnitState:
    """What the gateway knows about one unit right now."""

    ref: UnitRef
    faults: FaultTracker
    latest: dict[str, tuple[float, JSONObject]] = field(default_factory=dict)
    first_seen: float | None = None
    last_seen: float | None = None
    status_flags: JSONObject | None = None
    dm1: tuple[JSONValue, JSONValue] | None = None  # (lamps, dtcs) of the latest DM1
    series: int | None = None
    model: str | None = None
    software_id: str | None = None
    dirty: set[str] = field(default_factory=set)  # live slots not yet persisted
    seen_since_flush: list[float] | None = None  # [first, last] frame ts not yet persisted
    # Units whose frames arrive late and in batches (edge-forwarded streams): their monitors
    # run in the uploaded frames' time, so a forwarder out of range opens no OFFLINE episode.
    # For them, online also needs their latest frame within `fresh_within_s` of this
    # process's clock, and received (`received_at`, this process's clock) within it too.
    fresh_within_s: float | None = None
    received_at: float | None = None

    @property
    def parked_since(self) -> float | None:
        """When the unit fell silent with its whole bus (None: not parked)."""
        return self.faults.parked_since

    @property
    def name(self) -> str | None:
        """The J1939 NAME (hex) of the node holding the unit's address, from its address
        claim; None when no claim was seen."""
        claim = self.latest.get(CLAIM_SLOT)
        value = claim[1].get("name") if claim is not None else None
        return value if isinstance(value, str) else None

    def is_present(self) -> bool:
        """Heard at least once, and neither offline (an OFFLINE episode open) nor parked: what
        a command needs of every unit it reaches (`CommandService._check_online`). A unit
        never heard (configured, or mirrored from another gateway before its first frame was
        stored) is not present."""
        return (
            self.last_seen is not None
            and OFFLINE not in self.faults.open
            and self.faults.parked_since is None
        )

    def is_online(self, now: float | None = None) -> bool:
        """Present (`is_present`) and, for a unit fed in batches, recently heard."""
        if not self.is_present():
            return False
        if self.fresh_within_s is None:
            return True
        now = time.time() if now is None else now
        limit = self.fresh_within_s
        heard = (self.last_seen, self.received_at)
        return all(t is not None and now - t <= limit for t in heard)

    def state(self, now: float | None = None) -> str:
        """`online`, `offline` (silent while its bus carries traffic, or not recently heard
        when fed in batches) or `parked` (silent with its whole bus)."""
        if self.faults.parked_since is not None and OFFLINE not in self.faults.open:
            return UNIT_PARKED
        return UNIT_ONLINE if self.is_online(now) else UNIT_OFFLINE

    def snapshot(self) -> JSONObject:
        """JSON-ready view for the API and the dashboard."""
        return {
            **self.ref.to_dict(),
            "name": self.name,
            "series": self.series,
            "model": self.model,
            "software_id": self.software_id,
            "first_seen": self.first_seen,
            "last_seen": self.last_seen,
            "online": self.is_online(),
            "state": self.state(),
            "parked_since": self.faults.parked_since,
            "latest": {k: {"ts": ts, "fields": f} for k, (ts, f) in sorted(self.latest.items())},
            "faults": [ep.to_dict() for ep in self.faults.open.values()],
        }


UNIT_ONLINE, UNIT_OFFLINE, UNIT_PARKED = "online", "offline", "parked"
# A vehicle's state, worst first for people: not heard for `monitor.not_reporting_after_s`
# (or never); every bus silent (parked); a unit offline; a fault open; nothing to say.
NOT_REPORTING, PARKED, OFFLINE_STATE, ATTENTION, OK = (
    "not_reporting",
    "parked",
    "offline",
    "attention",
    "ok",
)
VEHICLE_STATES = (OK, ATTENTION, OFFLINE_STATE, PARKED, NOT_REPORTING)


@dataclass(frozen=True, slots=True)
class VehicleStatus:
    """A vehicle's state from its units' live state at one time."""

    state: str
    last_heard: float | None  # its units' latest frame
    parked_since: float | None  # when its bus fell silent (parked only)
    lead: tuple[str, int] | None  # the unit that carries the vehicle's own events and alerts

    def to_dict(self) -> JSONObject:
        return {
            "state": self.state,
            "last_heard": self.last_heard,
            "parked_since": self.parked_since,
        }


def vehicle_status(
    units: Iterable[UnitState], now: float, not_reporting_after_s: float
) -> VehicleStatus:
    """The state of the vehicle of `units` at `now` (see VEHICLE_STATES)."""
    heard: float | None = None
    parked: float | None = None
    lead: tuple[str, int] | None = None
    any_parked = any_offline = any_fault = False
    all_silent = True
    for u in units:
        key = u.ref.key
        if lead is None or key < lead:
            lead = key
        if u.last_seen is not None and (heard is None or u.last_seen > heard):
            heard = u.last_seen
        state = u.state(now)
        if state == UNIT_PARKED:
            any_parked = True
            since = u.faults.parked_since
            if since is not None and (parked is None or since > parked):
                parked = since
        elif state == UNIT_OFFLINE:
            any_offline = True
        else:
            all_silent = False
        if any(f != OFFLINE for f in u.faults.open):
            any_fault = True
    if heard is None or now - heard > not_reporting_after_s:
        return VehicleStatus(NOT_REPORTING, heard, parked if any_parked else None, lead)
    if any_parked and all_silent:  # an offline unit stays offline (and alerted) when parked
        return VehicleStatus(PARKED, heard, parked, lead)
    if any_offline:
        return VehicleStatus(OFFLINE_STATE, heard, None, lead)
    return VehicleStatus(ATTENTION if any_fault else OK, heard, None, lead)


class UnitTable(dict[tuple[str, int], UnitState]):
    """Units by (bus, SA), also indexed by vehicle, so a fleet listing is linear, not quadratic.

    Item assignment and deletion (what the pipeline and the cluster fan-out use) keep the index.
    """

    def __init__(self) -> None:
        super().__init__()
        self.by_vehicle: dict[str, dict[tuple[str, int], UnitState]] = {}

    def __setitem__(self, key: tuple[str, int], unit: UnitState) -> None:
        old = self.get(key)
        if old is not None:
            self._unindex(key, old)
        super().__setitem__(key, unit)
        self.by_vehicle.setdefault(unit.ref.vehicle_id, {})[key] = unit

    def __delitem__(self, key: tuple[str, int]) -> None:
        self._unindex(key, self[key])
        super().__delitem__(key)

    @overload
    def pop(self, key: tuple[str, int], /) -> UnitState: ...
    @overload
    def pop(self, key: tuple[str, int], default: UnitState, /) -> UnitState: ...
    @overload
    def pop(self, key: tuple[str, int], default: _T, /) -> UnitState | _T: ...
    def pop(self, key: tuple[str, int], /, *default: object) -> object:
        if key in self:
            unit = self[key]
            del self[key]
            return unit
        return super().pop(key, *default)

    def clear(self) -> None:
        super().clear()
        self.by_vehicle.clear()

    def _unindex(self, key: tuple[str, int], unit: UnitState) -> None:
        units = self.by_vehicle.get(unit.ref.vehicle_id)
        if units is not None:
            units.pop(key, None)
            if not units:
                del self.by_vehicle[unit.ref.vehicle_id]


def _heard_later(a: UnitState, b: UnitState) -> bool:
    return (a.last_seen or float("-inf")) > (b.last_seen or float("-inf"))


class LiveState:
    """Every unit's live state, by (bus, source address).

    `units` are the units of the pipeline that owns this view (monitored, persisted, mirrored
    from here). A bus `attach`ed shows another pipeline's units of that bus in the view, never
    ticked or persisted from it (an edge-forwarded stream, with its own pipeline): `get`,
    `of_vehicle`, `vehicle_ids` and `snapshot` include them; a unit in both is shown as the
    one heard from last.
    """

    def __init__(self) -> None:
        self.units = UnitTable()
        self.attached: dict[str, UnitTable] = {}  # bus -> its units, kept by another pipeline
        self._attached_buses: dict[str, set[str]] = {}  # vehicle id -> its attached buses

    def attach(self, bus: str, vehicle_id: str, units: UnitTable) -> None:
        """Show another pipeline's units of `bus` (a bus of `vehicle_id`), replacing what was
        attached for it."""
        self.detach(bus)
        self.attached[bus] = units
        self._attached_buses.setdefault(vehicle_id, set()).add(bus)

    def detach(self, bus: str) -> None:
        if self.attached.pop(bus, None) is None:
            return
        for vid, buses in list(self._attached_buses.items()):
            buses.discard(bus)
            if not buses:
                del self._attached_buses[vid]

    def get(self, bus: str, sa: int) -> UnitState | None:
        st = self.units.get((bus, sa))
        table = self.attached.get(bus)
        if table is not None:
            other = table.get((bus, sa))
            if other is not None and (st is None or _heard_later(other, st)):
                st = other
        return st

    def of_vehicle(self, vehicle_id: str) -> list[UnitState]:
        own = self.units.by_vehicle.get(vehicle_id, {})
        buses = self._attached_buses.get(vehicle_id)
        if not buses:
            return list(own.values())
        merged = dict(own)
        for bus in buses:
            for key, st in self.attached[bus].items():
                cur = merged.get(key)
                if cur is None or _heard_later(st, cur):
                    merged[key] = st
        return list(merged.values())

    def all_units(self) -> list[UnitState]:
        """Every unit in the view, attached ones included (one per (bus, SA), as `get`)."""
        if not self.attached:
            return list(self.units.values())
        merged: dict[tuple[str, int], UnitState] = dict(self.units)
        for table in self.attached.values():
            for key, st in table.items():
                cur = merged.get(key)
                if cur is None or _heard_later(st, cur):
                    merged[key] = st
        return list(merged.values())

    def vehicle_ids(self) -> set[str]:
        """Vehicles with at least one unit."""
        ids = set(self.units.by_vehicle)
        for vid, buses in self._attached_buses.items():
            if any(self.attached[b] for b in buses):
                ids.add(vid)
        return ids

    def snapshot(self, vehicle_id: str | None = None) -> list[JSONObject]:
        """Live state of every unit (of one vehicle, if given)."""
        if vehicle_id is not None:
            units = self.of_vehicle(vehicle_id)
        elif not self.attached:
            units = list(self.units.values())
        else:
            units = [u for vid in self.vehicle_ids() for u in self.of_vehicle(vid)]
        return [u.snapshot() for u in sorted(units, key=lambda u: (u.ref.bus, u.ref.sa))]
