"""Shared fixtures: a clean SQLite file and a clean PostgreSQL schema per test."""

from __future__ import annotations

import os
import uuid
from collections.abc import Iterator
from pathlib import Path

import pytest
from sqlalchemy import Engine, text

# The shared server of this machine; override with EQGW_TEST_PG (a URL without search_path).
PG_ADMIN_URL = os.environ.get("EQGW_TEST_PG", "postgresql+psycopg://postgres@127.0.0.1:5432/test")

_pg_problem: str | None = None
_pg_checked = False


def pg_unavailable_reason() -> str | None:
    """Why the PostgreSQL tests cannot run here (None when the server answers)."""
    global _pg_checked, _pg_problem
    if _pg_checked:
        return _pg_problem
    _pg_checked = True
    from eqgw.store.engine import create_engine

    engine = create_engine(PG_ADMIN_URL, connect_args={"connect_timeout": 3})
    try:
        with engine.connect() as conn:
            conn.execute(text("SELECT 1"))
    except Exception as exc:
        first = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        _pg_problem = f"PostgreSQL not reachable at {PG_ADMIN_URL} ({first})"
    finally:
        engine.dispose()
    return _pg_problem


def _sqlite_url(tmp_path: Path) -> str:
    return f"sqlite:///{tmp_path / 'eqgw.db'}"


@pytest.fixture
def sqlite_url(tmp_path: Path) -> str:
    """URL of a fresh SQLite file (no tables yet)."""
    return _sqlite_url(tmp_path)


@pytest.fixture
def pg_url() -> Iterator[str]:
    """URL of a fresh, empty PostgreSQL schema on the shared server, dropped afterwards."""
    reason = pg_unavailable_reason()
    if reason:
        pytest.skip(reason)
    from eqgw.store.engine import create_engine

    schema = f"t_{uuid.uuid4().hex[:12]}"
    admin = create_engine(PG_ADMIN_URL)
    with admin.begin() as conn:
        conn.execute(text(f'CREATE SCHEMA "{schema}"'))
    try:
        yield f"{PG_ADMIN_URL}?options=-csearch_path%3D{schema}"
    finally:
        with admin.begin() as conn:
            conn.execute(text(f'DROP SCHEMA "{schema}" CASCADE'))
            # The time partitions' schema (eqgw.store.partitions), emptied by the drop above.
            conn.execute(text(f'DROP SCHEMA IF EXISTS "{schema}_partitions" CASCADE'))
        admin.dispose()


@pytest.fixture(params=["sqlite", pytest.param("postgres", marks=pytest.mark.postgres)])
def db_url(request: pytest.FixtureRequest, tmp_path: Path) -> str:
    """Each test that uses it runs once on SQLite and once on PostgreSQL (empty database)."""
    if request.param == "sqlite":
        return _sqlite_url(tmp_path)
    url: str = request.getfixturevalue("pg_url")
    return url


@pytest.fixture
def engine(db_url: str) -> Iterator[Engine]:
    """A sync engine on a database migrated to the latest revision."""
    from eqgw.store.engine import create_engine
    from eqgw.store.migrate import upgrade_engine

    eng = create_engine(db_url)
    upgrade_engine(eng)
    try:
        yield eng
    finally:
        eng.dispose()
