"""Scenario files: which vehicles a simulated fleet has and what happens to them when.

A scenario is a small YAML or TOML file::

    seed: 7                      # optional; --seed overrides
    vehicles:                    # optional; unnamed vehicles are SIM-001, SIM-002, ...
      - name: COACH-12
        units: [{sa: 30, series: 80, rating: 60}, {sa: 31, series: 80, rating: 60}]
        battery_ah: 100
        soc: 0.9                 # or soc_a / soc_b
        load_12v: 20             # standing loads, amps
        load_24v: 5
        alternator: true
    events:
      - at: 30s                  # simulated time after the start: 90, "90s", "10m", "8h", "1h30m"
        vehicle: COACH-12        # a name, or "all"
        action: add_12v_load
        amps: 110
        for: 20m                 # optional: undo the action this much later
"""

from __future__ import annotations

import re
import tomllib
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from eqgw.sim.equalizer import EqualizerSpec
from eqgw.sim.vehicle import VehicleSpec

# action -> (argument names it takes, the action that undoes it)
ACTIONS: dict[str, tuple[frozenset[str], str | None]] = {
    "add_12v_load": (frozenset({"amps", "name"}), "remove_12v_load"),
    "remove_12v_load": (frozenset({"name"}), None),
    "add_24v_load": (frozenset({"amps", "name"}), "remove_24v_load"),
    "remove_24v_load": (frozenset({"name"}), None),
    "add_load_on_b": (frozenset({"amps", "name"}), "remove_load_on_b"),
    "remove_load_on_b": (frozenset({"name"}), None),
    "set_base_loads": (frozenset({"load_12v", "load_24v"}), None),
    "alternator_off": (frozenset(), "alternator_on"),
    "alternator_on": (frozenset({"volts"}), None),
    "jump_start": (frozenset({"volts"}), "end_jump_start"),
    "end_jump_start": (frozenset(), None),
    "fail_battery_b": (frozenset(), "restore_battery_b"),
    "restore_battery_b": (frozenset(), None),
    "fail_equalizer": (frozenset({"sa"}), "restore_equalizer"),
    "restore_equalizer": (frozenset({"sa"}), None),
    "stop_heartbeat": (frozenset({"sa", "mode"}), "restore_heartbeat"),
    "restore_heartbeat": (frozenset({"sa"}), None),
    "disconnect_bus": (frozenset(), "reconnect_bus"),
    "reconnect_bus": (frozenset(), None),
    "ignition_off": (frozenset(), "ignition_on"),
    "ignition_on": (frozenset(), None),
    "disconnect_unit": (frozenset({"sa"}), "reconnect_unit"),
    "reconnect_unit": (frozenset({"sa"}), None),
    "set_soc": (frozenset({"a", "b"}), None),
    "set_temperature": (frozenset({"celsius"}), None),
}
# Arguments the undo action keeps from the original (a load's name, a unit's SA).
_UNDO_KEEPS = frozenset({"name", "sa"})

_NUM = r"(\d+(?:\.\d+)?)"
_DURATION = re.compile(rf"^\s*(?:{_NUM}h)?\s*(?:{_NUM}m)?\s*(?:{_NUM}s?)?\s*$")


class ScenarioError(ValueError):
    """A scenario file that cannot be used, with the reason."""


def parse_duration(value: object) -> float:
    """Seconds from 90, 90.5, "90s", "10m", "8h" or "1h30m"."""
    if isinstance(value, bool):
        raise ScenarioError(f"not a duration: {value!r}")
    if isinstance(value, int | float):
        seconds = float(value)
    elif isinstance(value, str):
        m = _DURATION.match(value)
        if not m or not any(m.groups()):
            raise ScenarioError(f"not a duration: {value!r} (use 90, '90s', '10m', '1h30m')")
        h, mi, s = (float(g) if g else 0.0 for g in m.groups())
        seconds = h * 3600 + mi * 60 + s
    else:
        raise ScenarioError(f"not a duration: {value!r}")
    if seconds < 0:
        raise ScenarioError(f"negative duration: {value!r}")
    return seconds


@dataclass(frozen=True)
class Event:
    """One scripted action on one vehicle (or "all") at a simulated time after the start."""

    at: float
    vehicle: str
    action: str
    args: Mapping[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.action not in ACTIONS:
            raise ScenarioError(f"unknown action {self.action!r}; known: {sorted(ACTIONS)}")
        allowed, _ = ACTIONS[self.action]
        unknown = set(self.args) - allowed
        if unknown:
            raise ScenarioError(f"{self.action} takes {sorted(allowed)}, not {sorted(unknown)}")


@dataclass
class Scenario:
    """Vehicles and timed events; `events` is sorted by time."""

    vehicles: list[VehicleSpec] = field(default_factory=list)
    events: list[Event] = field(default_factory=list)
    seed: int | None = None
    name: str = "scenario"

    def __post_init__(self) -> None:
        self.events.sort(key=lambda e: e.at)


def _unit(raw: object, where: str) -> EqualizerSpec:
    if not isinstance(raw, Mapping):
        raise ScenarioError(f"{where}: a unit is a mapping like {{sa: 30, series: 80}}")
    unknown = set(raw) - {"sa", "series", "rating", "hardware_revision", "software_revision"}
    if unknown:
        raise ScenarioError(f"{where}: unknown unit keys {sorted(unknown)}")
    try:
        return EqualizerSpec(
            sa=int(raw.get("sa", 30)),
            series=int(raw.get("series", 80)),
            rating_a=int(raw.get("rating", 100)),
            hardware_revision=int(raw.get("hardware_revision", 1)),
            software_revision=int(raw.get("software_revision", 1)),
        )
    except (TypeError, ValueError) as exc:
        raise ScenarioError(f"{where}: {exc}") from exc


_VEHICLE_KEYS = {
    "name",
    "units",
    "series",
    "rating",
    "battery_ah",
    "soc",
    "soc_a",
    "soc_b",
    "soh_a",
    "soh_b",
    "load_12v",
    "load_24v",
    "alternator",
    "alternator_v",
    "temperature_c",
    "request_byte_order",
}


def _vehicle(raw: object, index: int) -> VehicleSpec:
    where = f"vehicles[{index}]"
    if not isinstance(raw, Mapping) or "name" not in raw:
        raise ScenarioError(f"{where}: a vehicle is a mapping with at least a name")
    unknown = set(raw) - _VEHICLE_KEYS
    if unknown:
        raise ScenarioError(f"{where}: unknown keys {sorted(unknown)}")
    units_raw = raw.get("units")
    if units_raw is None:
        units_raw = [{"sa": 30, "series": raw.get("series", 80), "rating": raw.get("rating", 100)}]
    if not isinstance(units_raw, list) or not units_raw:
        raise ScenarioError(f"{where}: units is a non-empty list")
    units = [_unit(u, f"{where}.units[{i}]") for i, u in enumerate(units_raw)]
    soc = raw.get("soc", 0.9)
    try:
        return VehicleSpec(
            name=str(raw["name"]),
            units=units,
            battery_ah=float(raw.get("battery_ah", 200.0)),
            soc_a=float(raw.get("soc_a", soc)),
            soc_b=float(raw.get("soc_b", soc)),
            soh_a=float(raw.get("soh_a", 1.0)),
            soh_b=float(raw.get("soh_b", 1.0)),
            load_12v_a=float(raw.get("load_12v", 10.0)),
            load_24v_a=float(raw.get("load_24v", 5.0)),
            alternator_on=bool(raw.get("alternator", True)),
            alternator_v=float(raw.get("alternator_v", 28.2)),
            temperature_c=float(raw.get("temperature_c", 20.0)),
            request_byte_order=str(raw.get("request_byte_order", "lsb")),
        )
    except (TypeError, ValueError) as exc:
        raise ScenarioError(f"{where}: {exc}") from exc


def _events(raw: object, index: int) -> list[Event]:
    where = f"events[{index}]"
    if not isinstance(raw, Mapping):
        raise ScenarioError(f"{where}: an event is a mapping with at, vehicle and action")
    for key in ("at", "vehicle", "action"):
        if key not in raw:
            raise ScenarioError(f"{where}: {key} is required")
    args = {k: v for k, v in raw.items() if k not in ("at", "vehicle", "action", "for")}
    at = parse_duration(raw["at"])
    action = str(raw["action"])
    try:
        event = Event(at, str(raw["vehicle"]), action, args)
    except ScenarioError as exc:
        raise ScenarioError(f"{where}: {exc}") from exc
    out = [event]
    if "for" in raw:
        undo = ACTIONS[action][1]
        if undo is None:
            raise ScenarioError(f"{where}: {action} has no undo, so 'for' does not apply")
        if action.startswith("add_") and "name" not in args:
            # The undo must remove this load, not every added one.
            args["name"] = f"event-{index}"
            out = [Event(at, event.vehicle, action, args)]
        kept = {k: v for k, v in args.items() if k in _UNDO_KEEPS and k in ACTIONS[undo][0]}
        out.append(Event(at + parse_duration(raw["for"]), event.vehicle, undo, kept))
    return out


def parse_scenario(data: object, name: str = "scenario") -> Scenario:
    """Build a scenario from already-parsed YAML/TOML data."""
    if data is None:
        data = {}
    if not isinstance(data, Mapping):
        raise ScenarioError("a scenario is a mapping with 'vehicles' and/or 'events'")
    unknown = set(data) - {"seed", "vehicles", "events", "name", "description"}
    if unknown:
        raise ScenarioError(f"unknown top-level keys {sorted(unknown)}")
    vehicles_raw = data.get("vehicles") or []
    events_raw = data.get("events") or []
    if not isinstance(vehicles_raw, list) or not isinstance(events_raw, list):
        raise ScenarioError("'vehicles' and 'events' are lists")
    vehicles = [_vehicle(v, i) for i, v in enumerate(vehicles_raw)]
    names = [v.name for v in vehicles]
    if len(set(names)) != len(names):
        raise ScenarioError(f"vehicle names must be unique: {names}")
    events = [e for i, raw in enumerate(events_raw) for e in _events(raw, i)]
    seed = data.get("seed")
    if seed is not None and (isinstance(seed, bool) or not isinstance(seed, int)):
        raise ScenarioError("seed is an integer")
    return Scenario(vehicles, events, seed, str(data.get("name", name)))


def load_scenario(path: str | Path) -> Scenario:
    """Read a scenario from a .yaml/.yml or .toml file."""
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except OSError as exc:
        raise ScenarioError(f"cannot read {p}: {exc}") from exc
    try:
        if p.suffix.lower() == ".toml":
            data: object = tomllib.loads(text)
        else:
            data = yaml.safe_load(text)
    except (yaml.YAMLError, tomllib.TOMLDecodeError) as exc:
        raise ScenarioError(f"{p}: {exc}") from exc
    return parse_scenario(data, p.stem)


def builtin_scenarios() -> dict[str, Path]:
    """The example scenarios shipped in app/sim/scenarios/, by file stem."""
    folder = Path(__file__).parent / "scenarios"
    return {p.stem: p for p in sorted(folder.glob("*")) if p.suffix in (".yaml", ".yml", ".toml")}
