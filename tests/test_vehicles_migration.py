"""`0014_vehicles_db` goes down and up again on a database that has vehicles, units and history.

The revision adds `vehicles.retired_at`; SQLite's batch copy of `vehicles` under the units that
refer to it failed with foreign keys on (`FOREIGN KEY constraint failed`), so a downgrade of a
real database did not work there. Both engines, with rows in every table that refers to a
vehicle.
"""

from __future__ import annotations

from alembic import command
from sqlalchemy import Engine, inspect, text

from eqgw.store.migrate import alembic_config, current_revision, head_revision

BELOW = "0012_rawblocks"  # the revision 0014_vehicles_db revises


def _rows(engine: Engine) -> dict[str, list[tuple[object, ...]]]:
    with engine.connect() as conn:
        return {
            "vehicles": [
                tuple(r)
                for r in conn.execute(text("SELECT id, name, depot FROM vehicles ORDER BY id"))
            ],
            "units": [
                tuple(r)
                for r in conn.execute(text("SELECT id, vehicle_id, bus, sa FROM units ORDER BY id"))
            ],
            "measurements": [
                tuple(r)
                for r in conn.execute(
                    text("SELECT unit_id, ts, v12, v24 FROM measurements ORDER BY unit_id, ts")
                )
            ],
        }


def test_vehicles_revision_downgrades_and_upgrades_with_units_present(
    engine: Engine, db_url: str
) -> None:
    assert current_revision(engine) == head_revision()
    with engine.begin() as conn:
        for vid, depot in (("V1", "North"), ("V2", None)):
            conn.execute(
                text("INSERT INTO vehicles (id, name, depot) VALUES (:id, :name, :depot)"),
                {"id": vid, "name": f"Bus {vid}", "depot": depot},
            )
        conn.execute(text("UPDATE vehicles SET retired_at = 1700000000.0 WHERE id = 'V2'"))
        for uid, vid, sa in ((1, "V1", 30), (2, "V1", 31), (3, "V2", 30)):
            conn.execute(
                text("INSERT INTO units (id, vehicle_id, bus, sa) VALUES (:id, :v, :bus, :sa)"),
                {"id": uid, "v": vid, "bus": f"{vid}/can0", "sa": sa},
            )
            conn.execute(
                text(
                    "INSERT INTO measurements (unit_id, ts, v12, v24, i12, i24)"
                    " VALUES (:u, :ts, 12.5, 25.05, NULL, 1.5)"
                ),
                {"u": uid, "ts": 1700000000.0 + uid},
            )
        conn.execute(
            text(
                "INSERT INTO vehicle_buses (name, vehicle_id, interface, channel, options,"
                " equalizer_sas, gateway_sa, request_byte_order, address_claim, stall_after_s,"
                " updated_at) VALUES ('V1/can0', 'V1', 'virtual', 'c0', '{}', '[30, 31]', 249,"
                " 'little', false, 5.0, 1700000000.0)"
            )
        )
    before = _rows(engine)
    cfg = alembic_config(db_url)

    command.downgrade(cfg, BELOW)

    assert current_revision(engine) == BELOW
    insp = inspect(engine)
    assert "retired_at" not in {c["name"] for c in insp.get_columns("vehicles")}
    assert "vehicle_buses" not in insp.get_table_names()
    assert "fleet_revision" not in insp.get_table_names()
    assert _rows(engine) == before  # no vehicle, unit or measurement lost on the way down
    fks = insp.get_foreign_keys("units")
    assert [(fk["referred_table"], fk["referred_columns"]) for fk in fks] == [("vehicles", ["id"])]

    command.upgrade(cfg, "head")

    assert current_revision(engine) == head_revision()
    assert _rows(engine) == before
    with engine.connect() as conn:
        retired = conn.execute(text("SELECT retired_at FROM vehicles ORDER BY id")).all()
    assert [r[0] for r in retired] == [None, None]  # retirement is 0014's: gone and back empty
