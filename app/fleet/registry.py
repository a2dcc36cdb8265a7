"""The fleet kept in the database: loading it, seeding it from the fleet file, changing it.

The database is the fleet's authority once it holds one: the fleet file's `[[vehicles]]` and
`[[buses]]` seed a database that never had a fleet, and are not applied after that (the
gateway says so when they differ). Every change (the API, `eqgw vehicles import`) is made in
one transaction that takes the fleet's lock, checks the whole result and raises the fleet's
version; gateways follow the version (eqgw.fleet.sync).

There is one validation path: a vehicle is an eqgw.config.VehicleConfig, a bus an
eqgw.bus.config.BusConfig, and the whole fleet passes eqgw.config.check_fleet, as the fleet
file does. Deleting a vehicle retires it: its buses go, its history stays, and creating its id
again brings the history back. A bus name that holds the history of another vehicle's units
cannot be given to a new bus (the units, and their history, would move to it).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Literal

from pydantic import ValidationError
from sqlalchemy import Connection, Engine

from eqgw.bus.config import BusConfig
from eqgw.config import AddressClaimSettings, Settings, VehicleConfig, check_fleet
from eqgw.fleet import repository as repo
from eqgw.security.keys import EVERYTHING, Scope

log = logging.getLogger(__name__)

SEEDED_BY_FILE = "the fleet file"
Mode = Literal["create", "update", "merge", "replace", "delete"]
Kind = Literal["added", "changed", "unchanged", "removed", "untouched"]


class FleetError(Exception):
    """A fleet change that cannot be made; `outcome` says why, row by row."""

    def __init__(self, outcome: Outcome) -> None:
        super().__init__(outcome.summary())
        self.outcome = outcome


@dataclass(frozen=True, slots=True)
class Fleet:
    """The fleet as the database holds it: vehicles by id, buses by name (as stored: a bus's
    own `address_claim_name` only, never one derived from `[address_claim]`)."""

    version: int
    vehicles: dict[str, VehicleConfig]
    buses: dict[str, BusConfig]
    # Rows that do not validate (edited by hand): left out, with the reason.
    invalid: tuple[str, ...] = ()

    def buses_of(self, vehicle_id: str) -> list[BusConfig]:
        return [b for b in self.buses.values() if b.vehicle_id == vehicle_id]


def bus_row(bus: BusConfig) -> dict[str, Any]:
    """A bus as a `vehicle_buses` row (its NAME, a 64-bit unsigned, as 0x hex text)."""
    name = bus.address_claim_name
    return {
        "name": bus.name,
        "vehicle_id": bus.vehicle_id,
        "interface": bus.interface,
        "channel": bus.channel,
        "bitrate": bus.bitrate,
        "options": dict(bus.options),
        "equalizer_sas": list(bus.equalizer_sas),
        "gateway_sa": bus.gateway_sa,
        "request_byte_order": bus.request_byte_order,
        "address_claim": bus.address_claim,
        "address_claim_name": None if name is None else f"0x{name:016X}",
        "stall_after_s": bus.stall_after_s,
    }


def bus_of_row(row: Mapping[str, Any]) -> BusConfig:
    """A `vehicle_buses` row as a checked BusConfig (ValidationError if it is not one)."""
    return BusConfig.model_validate({k: row[k] for k in (*repo.BUS_COLUMNS, "vehicle_id")})


def same_bus(a: BusConfig, b: BusConfig) -> bool:
    """Whether two buses are configured alike (as stored)."""
    return bus_row(a) == bus_row(b)


def stored_bus(bus: BusConfig, claim: AddressClaimSettings) -> BusConfig:
    """A bus of the fleet file as the database keeps it: without the NAME `[address_claim]`
    derived for it (each gateway derives that from its own settings)."""
    name = bus.address_claim_name
    if (
        name is not None
        and bus.address_claim
        and claim.enabled
        and claim.name is None
        and name == claim.name_for(bus.name)
    ):
        return bus.model_copy(update={"address_claim_name": None})
    return bus


def load(conn: Connection) -> Fleet:
    """The fleet in the database."""
    vehicles = {
        r["id"]: VehicleConfig.model_construct(id=r["id"], name=r["name"], depot=r["depot"])
        for r in repo.vehicles(conn)
    }
    buses: dict[str, BusConfig] = {}
    invalid: list[str] = []
    for row in repo.buses(conn):
        try:
            bus = bus_of_row(row)
        except ValidationError as exc:
            invalid.append(f"bus {row['name']!r}: {reasons(exc)}")
            continue
        if bus.vehicle_id in vehicles:
            buses[bus.name] = bus
    return Fleet(repo.version(conn) or 0, vehicles, buses, tuple(invalid))


def reasons(exc: ValidationError) -> str:
    """A validation error's reasons on one line (`field: why; ...`)."""
    out = []
    for err in exc.errors():
        where = ".".join(str(p) for p in err["loc"])
        msg = str(err["msg"]).removeprefix("Value error, ")
        out.append(f"{where}: {msg}" if where else msg)
    return "; ".join(out)


def _writer(engine: Engine) -> Engine:
    # SQLite: the write lock from the start (a deferred transaction that reads, then writes,
    # fails at once while the ingest writer holds the lock instead of waiting for it).
    return engine.execution_options(sqlite_begin="IMMEDIATE")


# -- seeding from the fleet file ---------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class SeedResult:
    """What starting with a fleet file did: seeded an empty database, or found the database
    holding the fleet already (and which of the file's vehicles and buses differ from it)."""

    seeded: bool
    fleet: Fleet
    seeded_at: float | None = None
    seeded_from: str | None = None
    differ: tuple[str, ...] = ()  # the file's vehicles and buses the database has otherwise


def seed(
    engine: Engine,
    vehicles: Sequence[VehicleConfig],
    buses: Sequence[BusConfig],
    claim: AddressClaimSettings,
) -> SeedResult:
    """Seed a database that has no fleet yet with the fleet file's vehicles and buses (a file
    without any seeds nothing: the database stays open to its first change); on a database that
    has one, compare. One transaction."""
    now = time.time()
    with _writer(engine).begin() as conn:
        rev = repo.revision(conn)
        if rev is None and (vehicles or buses):
            repo.lock(conn, now, SEEDED_BY_FILE)
            for v in vehicles:
                repo.put_vehicle(conn, v.id, v.display_name, v.depot)
            repo.put_buses(conn, [bus_row(stored_bus(b, claim)) for b in buses], now)
            repo.bump(conn, now)
            return SeedResult(True, load(conn), now, SEEDED_BY_FILE)
        fleet = load(conn)
    differ = []
    for v in vehicles:
        have = fleet.vehicles.get(v.id)
        if have is None or (have.display_name, have.depot) != (v.display_name, v.depot):
            differ.append(f"vehicle {v.id}")
    for b in buses:
        stored = fleet.buses.get(b.name)
        if stored is None or not same_bus(stored, stored_bus(b, claim)):
            differ.append(f"bus {b.name}")
    return SeedResult(
        False,
        fleet,
        None if rev is None else rev["seeded_at"],
        None if rev is None else rev["seeded_from"],
        tuple(differ),
    )


# -- changes -----------------------------------------------------------------------------------


@dataclass(slots=True)
class VehicleSpec:
    """A vehicle as it is to be: its configuration and its complete list of buses (`line`:
    where a CSV import gave it, and each bus's line)."""

    vehicle: VehicleConfig
    buses: list[BusConfig] = field(default_factory=list)
    line: int | None = None
    bus_lines: dict[str, int] = field(default_factory=dict)


@dataclass(frozen=True, slots=True)
class Problem:
    """Why a change cannot be made: a reason, the HTTP status it stands for, where."""

    reason: str
    status: int = 422
    line: int | None = None
    vehicle_id: str | None = None

    def as_dict(self) -> dict[str, Any]:
        return {"line": self.line, "vehicle_id": self.vehicle_id, "reason": self.reason}


@dataclass(frozen=True, slots=True)
class Change:
    """What a change does (or would do) to one vehicle."""

    vehicle_id: str
    kind: Kind
    fields: tuple[str, ...] = ()  # changed: name, depot, buses
    buses_added: tuple[str, ...] = ()
    buses_changed: tuple[str, ...] = ()
    buses_removed: tuple[str, ...] = ()
    line: int | None = None

    def as_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {"id": self.vehicle_id, "line": self.line}
        if self.kind == "changed":
            out["fields"] = list(self.fields)
        if self.kind in ("added", "changed"):
            out["buses_added"] = list(self.buses_added)
        if self.kind == "changed":
            out["buses_changed"] = list(self.buses_changed)
        if self.kind in ("changed", "removed"):
            out["buses_removed"] = list(self.buses_removed)
        return out


@dataclass(slots=True)
class Outcome:
    """The result of a fleet change: what it did (or, in a dry run or refused, would do)."""

    mode: Mode
    dry_run: bool
    changes: list[Change] = field(default_factory=list)
    problems: list[Problem] = field(default_factory=list)
    version: int = 0
    applied: bool = False
    fleet: Fleet | None = None  # the fleet after the change (or as it is, when not applied)

    def of(self, kind: Kind) -> list[Change]:
        return [c for c in self.changes if c.kind == kind]

    @property
    def changes_anything(self) -> bool:
        return any(c.kind in ("added", "changed", "removed") for c in self.changes)

    @property
    def status(self) -> int:
        """The HTTP status of a refusal: 403 when a row is outside the caller's scope, else
        the problems' own (404, 409), else 422."""
        statuses = {p.status for p in self.problems}
        for status in (403, 404, 409):
            if status in statuses:
                return status
        return 422

    def summary(self) -> str:
        if self.problems:
            n = len(self.problems)
            first = self.problems[0]
            where = f"line {first.line}: " if first.line is not None else ""
            more = f" (and {n - 1} more)" if n > 1 else ""
            return f"{where}{first.reason}{more}; nothing was changed"
        counts = ", ".join(f"{len(self.of(k))} {k}" for k in ("added", "changed", "removed"))
        return f"{counts} (fleet version {self.version})"

    def report(self) -> dict[str, Any]:
        """As the API and `eqgw vehicles import --json` answer it."""
        return {
            "dry_run": self.dry_run,
            "applied": self.applied,
            "mode": self.mode,
            "version": self.version,
            "added": [c.as_dict() for c in self.of("added")],
            "changed": [c.as_dict() for c in self.of("changed")],
            "unchanged": [c.vehicle_id for c in self.of("unchanged")],
            "removed": [c.as_dict() for c in self.of("removed")],
            "untouched": [c.vehicle_id for c in self.of("untouched")],
            "bad_rows": [p.as_dict() for p in self.problems],
        }


@dataclass(slots=True)
class Edit:
    """The vehicles a change sets (whole: configuration and every bus) and those it removes."""

    specs: list[VehicleSpec] = field(default_factory=list)
    remove: list[str] = field(default_factory=list)
    problems: list[Problem] = field(default_factory=list)


def may_manage(scope: Scope, vehicle_id: str, depot: str | None) -> bool:
    """Whether a key of `scope` may manage a vehicle with this id in this depot."""
    if scope.everything:
        return True
    if vehicle_id in (scope.vehicles or ()):
        return True
    return depot is not None and depot in (scope.groups or ())


def _outside(depot: str | None) -> str:
    if depot is None:
        return "a vehicle of no depot is outside this key's scope"
    return f"depot {depot!r} is outside this key's scope"


AuditHook = Callable[[Connection, "Outcome"], None]


def change(
    engine: Engine,
    edit: Edit | Callable[[Fleet], Edit],
    *,
    mode: Mode,
    scope: Scope = EVERYTHING,
    dry_run: bool = False,
    origin: str = "the API",
    audit: AuditHook | None = None,
) -> Outcome:
    """Make a fleet change in one transaction under the fleet's lock: `edit` (or what it makes
    of the fleet as it is then) checked as a whole, applied only when nothing is wrong and it
    is not a dry run; `audit` writes its audit entries in the same transaction. Modes: create
    (every vehicle new), update (every vehicle exists), merge (an import: add or change),
    replace (merge, and remove the vehicles in the caller's scope that the edit leaves out),
    delete (remove `edit.remove`)."""
    now = time.time()
    with _writer(engine).connect() as conn, conn.begin() as tx:
        before = repo.lock(conn, now, origin)
        fleet = load(conn)
        fleet = Fleet(before, fleet.vehicles, fleet.buses, fleet.invalid)
        made = edit(fleet) if callable(edit) else edit
        outcome = Outcome(mode, dry_run, problems=list(made.problems), version=before)
        final = _plan(conn, fleet, made, outcome, scope, mode)
        if outcome.problems or dry_run or not outcome.changes_anything:
            tx.rollback()
            outcome.fleet = fleet
            return outcome
        _write(conn, fleet, made, outcome, now)
        outcome.version = repo.bump(conn, now)
        outcome.applied = True
        outcome.fleet = Fleet(outcome.version, final[0], final[1])
        if audit is not None:
            audit(conn, outcome)
    return outcome


def _plan(
    conn: Connection,
    fleet: Fleet,
    edit: Edit,
    outcome: Outcome,
    scope: Scope,
    mode: Mode,
) -> tuple[dict[str, VehicleConfig], dict[str, BusConfig]]:
    """Check `edit` against the fleet and the caller's scope; record the changes and problems
    in `outcome`; return the fleet it makes (vehicles, buses)."""
    problems = outcome.problems
    specs = edit.specs
    remove = list(edit.remove)
    for vid in remove:
        have = fleet.vehicles.get(vid)
        if have is None or not may_manage(scope, vid, have.depot):
            problems.append(Problem(f"no vehicle {vid!r}", 404, vehicle_id=vid))
    named = {s.vehicle.id for s in specs}
    if mode == "replace":
        # A vehicle whose rows are bad is not one the file leaves out.
        named |= {p.vehicle_id for p in edit.problems if p.vehicle_id}
        remove += [
            vid
            for vid, v in fleet.vehicles.items()
            if vid not in named and may_manage(scope, vid, v.depot)
        ]
    for spec in specs:
        v = spec.vehicle
        have = fleet.vehicles.get(v.id)
        if not may_manage(scope, v.id, v.depot):
            problems.append(Problem(_outside(v.depot), 403, spec.line, v.id))
        elif mode == "create" and have is not None:
            problems.append(Problem(f"vehicle {v.id!r} exists", 409, spec.line, v.id))
        elif have is not None and not may_manage(scope, v.id, have.depot):
            if mode == "update":
                problems.append(Problem(f"no vehicle {v.id!r}", 404, spec.line, v.id))
            else:
                problems.append(
                    Problem(f"vehicle {v.id!r} is outside this key's scope", 403, spec.line, v.id)
                )
        elif mode == "update" and have is None:
            problems.append(Problem(f"no vehicle {v.id!r}", 404, spec.line, v.id))
    # Bus names: unique in the fleet; a name with another vehicle's history is not reused.
    touched = {s.vehicle.id for s in specs} | set(remove)
    owners = {n: b.vehicle_id for n, b in fleet.buses.items() if b.vehicle_id not in touched}
    given: dict[str, tuple[str, int | None]] = {}
    for spec in specs:
        for bus in spec.buses:
            line = spec.bus_lines.get(bus.name, spec.line)
            if bus.name in given:
                first = given[bus.name][1]
                at = f" (line {first})" if first is not None else ""
                problems.append(
                    Problem(f"bus {bus.name!r} is given twice{at}", 422, line, spec.vehicle.id)
                )
            elif bus.name in owners:
                problems.append(
                    Problem(
                        f"bus {bus.name!r} is a bus of another vehicle (bus names are unique "
                        "in the fleet)",
                        409,
                        line,
                        spec.vehicle.id,
                    )
                )
            given.setdefault(bus.name, (spec.vehicle.id, line))
    new_names = [
        n
        for n, (vid, _) in given.items()
        if n not in fleet.buses or fleet.buses[n].vehicle_id != vid
    ]
    for name, vids in repo.history_owners(conn, new_names).items():
        vid, line = given[name]
        if vids - {vid}:
            problems.append(
                Problem(
                    f"bus name {name!r} holds the history of another vehicle's units: give "
                    "this bus another name",
                    409,
                    line,
                    vid,
                )
            )
    # The fleet it makes, checked as the fleet file is.
    vehicles = {vid: v for vid, v in fleet.vehicles.items() if vid not in remove}
    buses = {n: b for n, b in fleet.buses.items() if b.vehicle_id not in touched}
    for spec in specs:
        vehicles[spec.vehicle.id] = spec.vehicle
        for bus in spec.buses:
            buses.setdefault(bus.name, bus)
    if not problems:
        try:
            check_fleet(list(vehicles.values()), list(buses.values()))
        except ValueError as exc:
            problems.append(Problem(str(exc)))
    # What it does to each vehicle: not said of one with a problem (outside the caller's
    # scope, it would tell what another depot's vehicle is like).
    bad = {p.vehicle_id for p in problems}
    for spec in specs:
        if spec.vehicle.id not in bad:
            outcome.changes.append(_diff(fleet, spec))
    for vid in dict.fromkeys(remove):
        if vid in fleet.vehicles:
            gone = tuple(b.name for b in fleet.buses_of(vid))
            outcome.changes.append(Change(vid, "removed", buses_removed=gone))
    if mode in ("merge", "update"):
        outcome.changes += [
            Change(vid, "untouched")
            for vid, v in fleet.vehicles.items()
            if vid not in touched and may_manage(scope, vid, v.depot)
        ]
    return vehicles, buses


def _diff(fleet: Fleet, spec: VehicleSpec) -> Change:
    v = spec.vehicle
    have = fleet.vehicles.get(v.id)
    new_buses = {b.name: b for b in spec.buses}
    if have is None:
        return Change(v.id, "added", buses_added=tuple(new_buses), line=spec.line)
    old_buses = {b.name: b for b in fleet.buses_of(v.id)}
    added = tuple(n for n in new_buses if n not in old_buses)
    removed = tuple(n for n in old_buses if n not in new_buses)
    changed = tuple(
        n for n in new_buses if n in old_buses and not same_bus(new_buses[n], old_buses[n])
    )
    fields = []
    if have.display_name != v.display_name:
        fields.append("name")
    if have.depot != v.depot:
        fields.append("depot")
    if added or removed or changed:
        fields.append("buses")
    if not fields:
        return Change(v.id, "unchanged", line=spec.line)
    return Change(v.id, "changed", tuple(fields), added, changed, removed, spec.line)


def _write(conn: Connection, fleet: Fleet, edit: Edit, outcome: Outcome, now: float) -> None:
    kinds = {c.vehicle_id: c for c in outcome.changes}
    for c in outcome.of("removed"):
        repo.retire_vehicle(conn, c.vehicle_id, now)
    # Every bus leaving a vehicle first: within one change a name may pass to another vehicle.
    leaving = [
        n
        for spec in edit.specs
        if kinds[spec.vehicle.id].kind == "changed"
        for n in kinds[spec.vehicle.id].buses_removed
    ]
    repo.remove_buses(conn, leaving)
    rows = []
    for spec in edit.specs:
        c = kinds[spec.vehicle.id]
        if c.kind not in ("added", "changed"):
            continue
        repo.put_vehicle(conn, spec.vehicle.id, spec.vehicle.display_name, spec.vehicle.depot)
        rows += [bus_row(b) for b in spec.buses if b.name in (*c.buses_added, *c.buses_changed)]
    repo.put_buses(conn, rows, now)


def fleet_version(engine: Engine) -> int:
    """The fleet's version now (0: never seeded or changed)."""
    with engine.connect() as conn:
        return repo.version(conn) or 0


def load_fleet(engine: Engine) -> Fleet:
    """The fleet in the database now."""
    with engine.connect() as conn:
        return load(conn)


def in_effect(settings: Settings) -> Settings:
    """`settings` with the fleet in effect: the database's once it holds one, else the fleet
    file's (which will seed it); for the commands that read the fleet without serving it
    (`eqgw replay`, `eqgw keys rotate`). A database that cannot be read leaves the file's."""
    from sqlalchemy.exc import SQLAlchemyError

    from eqgw.store.engine import create_engine

    engine = create_engine(settings.database_url, deadlines=settings.db)
    try:
        with engine.connect() as conn:
            if repo.revision(conn) is None:
                return settings
            fleet = load(conn)
    except SQLAlchemyError:
        return settings
    finally:
        engine.dispose()
    buses = [settings.apply_address_claim(b.model_copy()) for b in fleet.buses.values()]
    return settings.model_copy(update={"vehicles": list(fleet.vehicles.values()), "buses": buses})


def depots_of(vehicles: Iterable[VehicleConfig]) -> dict[str, str | None]:
    return {v.id: v.depot for v in vehicles}
