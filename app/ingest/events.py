"""Events the ingest publishes on the hub (websocket, alerts and command confirmation read them)."""

from __future__ import annotations

from dataclasses import dataclass, field

from eqgw.jsontypes import JSONObject

# Event kinds. `record`: every decoded record; `live`: a unit's live value changed;
# `status_change`: status flags differ from the previous frame; `fault_open`, `fault_update`
# (source or occurrence count changed), `fault_stale`, `fault_close`: fault episodes;
# `unit_online`: first frame of a unit (or its first after being parked; after being offline,
# the OFFLINE episode's `fault_close` says it); `unit_parked`: the unit fell silent with its
# whole bus (`data`: parked_since, last_seen); `vehicle_state`: a vehicle's state changed
# (`data`: state, last_heard, parked_since; on the vehicle's lead unit, its lowest bus and SA).
RECORD = "record"
LIVE = "live"
STATUS_CHANGE = "status_change"
FAULT_OPEN = "fault_open"
FAULT_UPDATE = "fault_update"
FAULT_STALE = "fault_stale"
FAULT_CLOSE = "fault_close"
UNIT_ONLINE = "unit_online"
UNIT_PARKED = "unit_parked"
VEHICLE_STATE = "vehicle_state"
# What a unit's state is made of for readers outside the pipeline (websocket, alerts, other
# gateways): every ingest kind but `record`, the raw decode stream.
UNIT_KINDS = frozenset(
    {
        LIVE,
        STATUS_CHANGE,
        FAULT_OPEN,
        FAULT_UPDATE,
        FAULT_STALE,
        FAULT_CLOSE,
        UNIT_ONLINE,
        UNIT_PARKED,
        VEHICLE_STATE,
    }
)
INGEST_KINDS = UNIT_KINDS | {RECORD}
# Alert lifecycle (eqgw.alerts), `data` is the alert as the API shows it.
ALERT_RAISED = "alert_raised"
ALERT_ACKNOWLEDGED = "alert_acknowledged"
ALERT_CLEARED = "alert_cleared"
ALERT_KINDS = frozenset({ALERT_RAISED, ALERT_ACKNOWLEDGED, ALERT_CLEARED})
KINDS = INGEST_KINDS | ALERT_KINDS


@dataclass(frozen=True, slots=True)
class UnitRef:
    """A unit as the ingest knows it: its vehicle, bus and source address."""

    vehicle_id: str
    bus: str
    sa: int

    @property
    def key(self) -> tuple[str, int]:
        return (self.bus, self.sa)

    def to_dict(self) -> JSONObject:
        return {"vehicle_id": self.vehicle_id, "bus": self.bus, "sa": self.sa}


@dataclass(frozen=True, slots=True)
class Event:
    """One thing that happened on one unit at one (frame) time."""

    kind: str
    unit: UnitRef
    ts: float
    data: JSONObject = field(default_factory=dict)

    def to_dict(self) -> JSONObject:
        return {"kind": self.kind, "unit": self.unit.to_dict(), "ts": self.ts, "data": self.data}
