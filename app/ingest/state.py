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

    def pop(self, key: tuple[str, int], *default: Any) -> Any:
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


class LiveState:
    """Every unit's live state, by (bus, source address)."""

    def __init__(self) -> None:
        self.units = UnitTable()

    def get(self, bus: str, sa: int) -> UnitState | None:
        return self.units.get((bus, sa))

    def of_vehicle(self, vehicle_id: str) -> list[UnitState]:
        return list(self.units.by_vehicle.get(vehicle_id, {}).values())

    def vehicle_ids(self) -> set[str]:
        """Vehicles with at least one unit."""
        return set(self.units.by_vehicle)

    def snapshot(self, vehicle_id: str | None = None) -> list[dict[str, Any]]:
        """Live state of every unit (of one vehicle, if given)."""
        units = self.units.values() if vehicle_id is None else self.of_vehicle(vehicle_id)
        return [u.snapshot() for u in sorted(units, key=lambda u: (u.ref.bus, u.ref.sa))]
