"""Shared fixtures: a clean SQLite file and a clean PostgreSQL schema per test."""

from __future__ import annotations

import asyncio
import contextlib
import functools
import gc
import os
import sys
import uuid
from collections.abc import Iterator
from pathlib import Path

import pytest
from sqlalchemy import Engine, text

# Before any test module imports python-can: eqgw's import has python-can's MF4 module load
# without asammdf until a test reads or writes an MF4 log (eqgw.bus.mf4), so a test process
# does not carry asammdf's numpy, pandas and sympy (0.7 s of CPU, and 100,000s of objects that
# every full collection of the worker's heap would walk) for the tests that never use it.
import eqgw  # noqa: F401  isort: skip

from tests import proc_helpers
from tests.support import forked

# `eqgw` commands forked from a server that imported eqgw once per test process
# (tests/support/forked.py); EQGW_TEST_FORK=0 runs each in a new interpreter.
proc_helpers.FORK = forked.enabled()

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
    with _pg_schema() as url:
        yield url


@contextlib.contextmanager
def _pg_schema() -> Iterator[str]:
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


@pytest.fixture(
    scope="module", params=["sqlite", pytest.param("postgres", marks=pytest.mark.postgres)]
)
def module_db_url(
    request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory
) -> Iterator[str]:
    """`db_url` shared by the tests of a module that only read (a gateway booted once for
    them), on each engine."""
    if request.param == "sqlite":
        yield _migrated_sqlite_url(tmp_path_factory.mktemp("module-db"), tmp_path_factory)
        return
    with _pg_copy() as url:
        yield url


def _migrated_sqlite_url(folder: Path, tmp_path_factory: pytest.TempPathFactory) -> str:
    """URL of an SQLite file in `folder` at the head revision with nothing in it: a copy of
    a file migrated once per test process (tests/support/migrated.py)."""
    from tests.support import migrated

    scratch = tmp_path_factory.getbasetemp() / "migrated"
    scratch.mkdir(exist_ok=True)
    path = folder / "eqgw.db"
    migrated.copy_migrated_sqlite(path, scratch)
    return f"sqlite:///{path}"


@contextlib.contextmanager
def _pg_copy() -> Iterator[str]:
    """URL of a PostgreSQL database at the head revision with nothing in it, for the
    duration (a copy of a template migrated once per test process, reset for the next user:
    tests/support/migrated.py)."""
    from tests.support import migrated

    reason = pg_unavailable_reason()
    if reason:
        pytest.skip(reason)
    with migrated.migrated_pg_database(PG_ADMIN_URL) as url:
        yield url


@pytest.fixture(params=["sqlite", pytest.param("postgres", marks=pytest.mark.postgres)])
def db_url(
    request: pytest.FixtureRequest, tmp_path: Path, tmp_path_factory: pytest.TempPathFactory
) -> str:
    """Each test that uses it runs once on SQLite and once on PostgreSQL, on a database at
    the head revision with nothing in it (what a gateway's first start makes of an empty
    one): a copy of a database migrated once per test process (tests/support/migrated.py).
    A test of what happens to an empty database asks for `empty_db_url` or `sqlite_url`."""
    if request.param == "sqlite":
        return _migrated_sqlite_url(tmp_path, tmp_path_factory)
    url: str = request.getfixturevalue("_pg_migrated_url")
    return url


@pytest.fixture(params=["sqlite", pytest.param("postgres", marks=pytest.mark.postgres)])
def empty_db_url(request: pytest.FixtureRequest, tmp_path: Path) -> str:
    """`db_url` for a test of the migrations: an empty SQLite file or PostgreSQL schema."""
    if request.param == "sqlite":
        return _sqlite_url(tmp_path)
    url: str = request.getfixturevalue("pg_url")
    return url


@pytest.fixture
def _pg_migrated_url() -> Iterator[str]:
    """`_pg_copy` for one test."""
    with _pg_copy() as url:
        yield url


@pytest.fixture
def engine(db_url: str) -> Iterator[Engine]:
    """A sync engine on a database migrated to the latest revision (a copy of one migrated
    once per test process, tests/support/migrated.py)."""
    from eqgw.store.engine import create_engine
    from eqgw.store.migrate import upgrade_engine

    eng = create_engine(db_url)
    upgrade_engine(eng)  # a no-op on the copy: it is at the head revision
    try:
        yield eng
    finally:
        eng.dispose()


@pytest.fixture(autouse=True)
def no_leftovers(request: pytest.FixtureRequest) -> Iterator[None]:
    """Fail a test that leaves a thread, a child process, a listening socket, a virtual bus,
    a Notifier or an asyncio task running. Autouse and function-scoped, it is set up before and
    torn down after every other function-scoped fixture, so what those stop is not counted;
    what broader fixtures started is running before it and is not counted either."""
    from tests.support import leftovers

    loop = None
    tasks_before: set[asyncio.Task[object]] = set()
    loop_scope = getattr(request.node, "_loop_scope", None)  # a pytest-asyncio test
    if loop_scope is not None:
        # Asked for here, the test's event loop outlives this fixture: its tasks are still
        # there to be seen at teardown (the runner cancels them silently when it closes).
        loop = request.getfixturevalue(f"_{loop_scope}_scoped_runner").get_loop()
        tasks_before = asyncio.all_tasks(loop)
    before = leftovers.Snapshot.take()
    yield
    problems = leftovers.tasks_left(loop, tasks_before) if loop is not None else []
    problems += leftovers.settle(before, loop)
    assert not problems, "; ".join(problems)


@pytest.hookimpl(trylast=True)
def pytest_runtest_teardown(item: pytest.Item) -> None:
    """Empty FastAPI's caches of endpoint and dependency callables after each test. They
    are bounded (4,096 each) and hold the callables, and through their closures the apps: a
    gateway has one app for its life, a test worker builds hundreds, and with every app a test
    built kept alive (1.9 million objects after 75 tests of the API) each full collection of
    the worker's heap took over a second and a growing share of the suite's CPU."""
    models = sys.modules.get("fastapi.dependencies.models")
    for value in vars(models).values() if models is not None else ():
        if isinstance(value, functools._lru_cache_wrapper):
            value.cache_clear()


def pytest_collection_finish(session: pytest.Session) -> None:
    """The heap frozen once the tests are collected: what a test process holds for the whole
    run (every module it imported, the collected tests: 300,000+ objects) is out of the
    collector's sight, and each full collection walks only what the tests made since (tests
    that read or write large logs trigger many: run alone, the heaviest of them spent 1.41 s in
    the collector instead of 2.78 s). A gateway run in the test process leaves a frozen heap
    as it is (eqgw.api.lifespan.serving), told so once here instead of looking at each start
    (a look walks every frozen object: 20 ms of CPU, twice per gateway with tests/api_helpers'
    own look)."""
    from eqgw.api.lifespan import host_manages_collector

    gc.collect()
    gc.freeze()
    host_manages_collector()


@pytest.hookimpl(trylast=True)
def pytest_sessionfinish(session: pytest.Session) -> None:
    """One full collection of the heap after the last test, then the heap frozen: pytest's
    check for unraisable exceptions (`__del__` warnings: an unclosed connection, file or
    socket) collects five more times as the session ends, each a walk of everything a worker
    made in the run (17 s of the workers' time in a sampled profile of a full run, all of it
    at the very end). What
    this collection finds is reported by that check as before; the walks after it find
    nothing new and take no time."""
    gc.collect()
    gc.freeze()
    if _pg_checked and _pg_problem is None:
        from tests.support import migrated

        migrated.drop_pg_template(PG_ADMIN_URL)


@pytest.hookimpl(tryfirst=True)
def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Tests sharing a module-scoped fixture (a gateway, a browser) run on one xdist worker
    (`--dist loadgroup`), so it is set up once, not once a worker."""
    if not config.pluginmanager.hasplugin("xdist"):
        return  # `-p no:xdist`: one process, and no xdist_group marker to set
    for item in items:
        info = getattr(item, "_fixtureinfo", None)
        if info is None or item.get_closest_marker("xdist_group"):
            continue
        shared = any(
            defs[-1].scope in ("module", "class", "package") and defs[-1].baseid.startswith("tests")
            for defs in info.name2fixturedefs.values()
        )
        if shared:
            item.add_marker(pytest.mark.xdist_group(item.nodeid.split("::")[0]))
