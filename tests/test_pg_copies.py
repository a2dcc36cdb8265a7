"""The PostgreSQL copies the tests get (tests/support/migrated.py) are used again only when
nothing of the test before is left in them: its rows, its sequence values, its sessions, its
changes to the template's own rows. A copy whose schema a test changed is dropped instead."""

from __future__ import annotations

import time

import pytest
from sqlalchemy import Connection, text

from eqgw.store.engine import create_engine
from tests.conftest import PG_ADMIN_URL, pg_unavailable_reason
from tests.support import migrated

pytestmark = pytest.mark.postgres


@pytest.fixture(autouse=True)
def _server() -> None:
    reason = pg_unavailable_reason()
    if reason:
        pytest.skip(reason)


def _name(url: str) -> str:
    return url.rsplit("/", 1)[1]


def _exists(name: str) -> bool:
    admin = create_engine(PG_ADMIN_URL)
    try:
        with admin.connect() as conn:
            found = conn.execute(
                text("SELECT count(*) FROM pg_database WHERE datname = :n"), {"n": name}
            ).scalar_one()
        return bool(found)
    finally:
        admin.dispose()


def _add_unit(conn: Connection, vehicle_id: str) -> int:
    """A vehicle with one unit; the unit's id (from its sequence)."""
    conn.execute(text("INSERT INTO vehicles (id, name) VALUES (:v, :v)"), {"v": vehicle_id})
    unit: int = conn.execute(
        text("INSERT INTO units (vehicle_id, bus, sa) VALUES (:v, 'can0', 128) RETURNING id"),
        {"v": vehicle_id},
    ).scalar_one()
    return unit


def test_a_copy_comes_back_as_the_template_whatever_the_test_left() -> None:
    now = time.time()
    # The copy a test gives back is the next one taken (the pool is a stack).
    with migrated.migrated_pg_database(PG_ADMIN_URL) as url:
        first = _name(url)
        engine = create_engine(url)
        try:
            with engine.begin() as conn:
                unit = _add_unit(conn, "V1")
                # A partitioned table, a row of the template changed, one added beside it.
                conn.execute(
                    text("INSERT INTO measurements (unit_id, ts, v12) VALUES (:u, :t, 12.5)"),
                    {"u": unit, "t": now},
                )
                conn.execute(text("UPDATE delivery_cursors SET last_event_id = 41"))
                conn.execute(
                    text(
                        "INSERT INTO delivery_cursors (name, last_event_id, updated_at) "
                        "VALUES ('other', 7, 0)"
                    )
                )
                conn.execute(
                    text(
                        "INSERT INTO audit_log (ts, action, outcome, status_code) "
                        "VALUES (0, 'a', 'ok', 200)"
                    )
                )
            # A session the test leaves behind, idle in a transaction that holds a lock.
            left = engine.connect()
            left.execute(text("LOCK TABLE vehicles IN ACCESS EXCLUSIVE MODE"))
        finally:
            engine.dispose(close=False)
    with migrated.migrated_pg_database(PG_ADMIN_URL) as url:
        assert _name(url) == first  # the same copy, used again
        engine = create_engine(url)
        try:
            with engine.connect() as conn:
                for table in ("vehicles", "units", "audit_log", "measurements"):
                    assert conn.execute(text(f"SELECT count(*) FROM {table}")).scalar() == 0
                assert conn.execute(
                    text("SELECT name, last_event_id FROM delivery_cursors")
                ).all() == [("webhooks", 0)]
            # The sequences start where the template's do: the next unit gets the same id.
            with engine.begin() as conn:
                again = _add_unit(conn, "V2")
            assert again == unit
            state = migrated._pg_template_state
            assert state is not None
        finally:
            engine.dispose()
        left.invalidate()  # its session was ended by the reset: nothing to roll back
        left.close()
    # What the test above wrote is gone again, and the whole state is the template's.
    with migrated.migrated_pg_database(PG_ADMIN_URL) as url:
        assert _name(url) == first
        engine = create_engine(url)
        try:
            assert migrated._State.of(engine) == state
        finally:
            engine.dispose()


def test_a_copy_whose_schema_changed_is_dropped_not_used_again() -> None:
    changes = [
        "CREATE TABLE extra (id int)",
        "ALTER TABLE vehicles ADD COLUMN colour text",
        "CREATE INDEX vehicles_name ON vehicles (name)",
        "ALTER TABLE vehicles ALTER COLUMN depot SET DEFAULT 'north'",
        "REVOKE ALL ON vehicles FROM PUBLIC; GRANT SELECT ON vehicles TO PUBLIC",
        "CREATE FUNCTION f() RETURNS int LANGUAGE sql AS 'SELECT 1'",
        # What a retention run does to a day's partition.
        "DROP TABLE public_partitions.measurements_default",
    ]
    for change in changes:
        with migrated.migrated_pg_database(PG_ADMIN_URL) as url:
            name = _name(url)
            engine = create_engine(url)
            try:
                with engine.begin() as conn:
                    conn.execute(text(change))
            finally:
                engine.dispose()
        assert not _exists(name), change
        with migrated.migrated_pg_database(PG_ADMIN_URL) as url:
            assert _name(url) != name, change
