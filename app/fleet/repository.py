"""The fleet's SQL: vehicles, their buses and the fleet's version (no validation here: rows in,
rows out; eqgw.fleet.registry turns them into checked configurations)."""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from typing import Any

from sqlalchemy import Connection, delete, func, select, update

from eqgw.fleet.models import FleetRevision, VehicleBus
from eqgw.store.models import Unit, Vehicle, table_of
from eqgw.store.writes import dialect_insert

_vehicles = table_of(Vehicle)
_buses = table_of(VehicleBus)
_revision = table_of(FleetRevision)
_units = table_of(Unit)

BUS_COLUMNS = tuple(c.name for c in _buses.columns if c.name not in ("vehicle_id", "updated_at"))


def revision(conn: Connection) -> dict[str, Any] | None:
    """The fleet's version row (version, changed_at, seeded_at, seeded_from); None: no fleet
    was ever seeded or changed in this database."""
    row = conn.execute(select(_revision).where(_revision.c.id == 1)).mappings().first()
    return dict(row) if row is not None else None


def version(conn: Connection) -> int | None:
    """The fleet's version alone (the query every gateway polls)."""
    value = conn.execute(select(_revision.c.version).where(_revision.c.id == 1)).scalar()
    return None if value is None else int(value)


def lock(conn: Connection, now: float, seeded_from: str) -> int:
    """Take the fleet's lock for this transaction (the version row, created at version 0 when
    missing): fleet changes are made one at a time, each on what the previous one left.
    Returns the version before the change."""
    ins = dialect_insert(conn, _revision).values(
        id=1, version=0, changed_at=now, seeded_at=now, seeded_from=seeded_from
    )
    conn.execute(ins.on_conflict_do_nothing(index_elements=["id"]))
    stmt = select(_revision.c.version).where(_revision.c.id == 1)
    if conn.dialect.name == "postgresql":
        stmt = stmt.with_for_update()
    return int(conn.execute(stmt).scalar_one())


def bump(conn: Connection, now: float) -> int:
    """Raise the fleet's version (after `lock` in the same transaction); returns the new one."""
    conn.execute(
        update(_revision)
        .where(_revision.c.id == 1)
        .values(version=_revision.c.version + 1, changed_at=now)
    )
    return int(conn.execute(select(_revision.c.version).where(_revision.c.id == 1)).scalar_one())


def vehicles(conn: Connection) -> list[dict[str, Any]]:
    """The fleet's vehicles (retired ones left out), by id."""
    stmt = (
        select(_vehicles.c.id, _vehicles.c.name, _vehicles.c.depot)
        .where(_vehicles.c.retired_at.is_(None))
        .order_by(_vehicles.c.id)
    )
    return [dict(r) for r in conn.execute(stmt).mappings()]


def buses(conn: Connection) -> list[dict[str, Any]]:
    """Every bus of the fleet's vehicles, by name."""
    stmt = select(_buses).order_by(_buses.c.name)
    return [dict(r) for r in conn.execute(stmt).mappings()]


def history_owners(conn: Connection, names: Iterable[str]) -> dict[str, set[str]]:
    """Per bus name of `names`, the vehicles whose units were heard on a bus of that name."""
    wanted = sorted(set(names))
    out: dict[str, set[str]] = {}
    for i in range(0, len(wanted), 500):
        stmt = (
            select(_units.c.bus, _units.c.vehicle_id)
            .where(_units.c.bus.in_(wanted[i : i + 500]))
            .group_by(_units.c.bus, _units.c.vehicle_id)
        )
        for bus, vid in conn.execute(stmt):
            out.setdefault(str(bus), set()).add(str(vid))
    return out


def put_vehicle(conn: Connection, vehicle_id: str, name: str, depot: str | None) -> None:
    """Create a vehicle, or change one (a retired one comes back)."""
    ins = dialect_insert(conn, _vehicles).values(
        id=vehicle_id, name=name, depot=depot, retired_at=None
    )
    conn.execute(
        ins.on_conflict_do_update(
            index_elements=["id"],
            set_={"name": ins.excluded.name, "depot": ins.excluded.depot, "retired_at": None},
        )
    )


def retire_vehicle(conn: Connection, vehicle_id: str, now: float) -> None:
    """Retire a vehicle: its buses go, its history stays."""
    conn.execute(delete(_buses).where(_buses.c.vehicle_id == vehicle_id))
    conn.execute(update(_vehicles).where(_vehicles.c.id == vehicle_id).values(retired_at=now))


def remove_buses(conn: Connection, names: Sequence[str]) -> None:
    for i in range(0, len(names), 500):
        conn.execute(delete(_buses).where(_buses.c.name.in_(list(names[i : i + 500]))))


def put_buses(conn: Connection, rows: Sequence[dict[str, Any]], now: float) -> None:
    """Insert or replace buses (rows of every column but `updated_at`)."""
    if not rows:
        return
    ins = dialect_insert(conn, _buses)
    columns = [c.name for c in _buses.columns if c.name != "name"]
    stmt = ins.on_conflict_do_update(
        index_elements=["name"], set_={c: ins.excluded[c] for c in columns}
    )
    conn.execute(stmt, [{**r, "updated_at": now} for r in rows])


def count_vehicles(conn: Connection) -> int:
    """The fleet's vehicles (retired ones left out)."""
    stmt = select(func.count()).select_from(_vehicles).where(_vehicles.c.retired_at.is_(None))
    return int(conn.execute(stmt).scalar_one())
