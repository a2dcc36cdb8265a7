"""Per-unit live state kept in memory: latest values, status flags, DM1, open fault episodes."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from app.ingest.events import UnitRef
from app.ingest.faults import FaultTracker


def live_key(name: str, fields: dict[str, Any]) -> str:
    """The live-state slot of a record: multiplexed messages keep one slot per index."""
    if name in ("battery_states", "parameters"):
        return f"{name}/{fields.get('index')}"
    return name


@dataclass(slots=True)
class UnitState:
    """What the gateway knows about one unit right now."""

    ref: UnitRef
    faults: FaultTracker
    latest: dict[str, tuple[float, dict[str, Any]]] = field(default_factory=dict)
    first_seen: float | None = None
    last_seen: float | None = None
    status_flags: dict[str, Any] | None = None
    dm1: tuple[Any, Any] | None = None  # (lamps, dtcs) of the latest DM1
    series: int | None = None
    model: str | None = None
    software_id: str | None = None
    dirty: set[str] = field(default_factory=set)  # live slots not yet persisted
    seen_since_flush: list[float] | None = None  # [first, last] frame ts not yet persisted

    def snapshot(self) -> dict[str, Any]:
        """JSON-ready view for the API and the dashboard."""
        return {
            **self.ref.to_dict(),
            "series": self.series,
            "model": self.model,
            "software_id": self.software_id,
            "first_seen": self.first_seen,
            "last_seen": self.last_seen,
            "online": "OFFLINE" not in self.faults.open,
            "latest": {k: {"ts": ts, "fields": f} for k, (ts, f) in sorted(self.latest.items())},
            "faults": [ep.to_dict() for ep in self.faults.open.values()],
        }


class LiveState:
    """Every unit's live state, by (bus, source address)."""

    def __init__(self) -> None:
        self.units: dict[tuple[str, int], UnitState] = {}

    def get(self, bus: str, sa: int) -> UnitState | None:
        return self.units.get((bus, sa))

    def of_vehicle(self, vehicle_id: str) -> list[UnitState]:
        return [u for u in self.units.values() if u.ref.vehicle_id == vehicle_id]

    def snapshot(self, vehicle_id: str | None = None) -> list[dict[str, Any]]:
        """Live state of every unit (of one vehicle, if given)."""
        units = self.units.values() if vehicle_id is None else self.of_vehicle(vehicle_id)
        return [u.snapshot() for u in sorted(units, key=lambda u: (u.ref.bus, u.ref.sa))]
