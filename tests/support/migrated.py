"""An SQLite database migrated once per test process and copied into each test's own file.

A migration of an empty SQLite file takes 0.1 s of CPU and 0.3-0.7 s in all (its commits wait
for the disk); a copy takes a millisecond. On PostgreSQL the server's own work dominates (DDL of
~50 tables and their partitions, 0.2 s of the server's CPU and 0.1 s of the client's; replaying
a dump of a migrated schema took as long): there the copy is a database made from a migrated
template database (`CREATE DATABASE ... TEMPLATE`, which copies its files: 0.01 s of the
server's CPU), one template per test process. The template also holds the time partitions a
gateway's first maintenance round makes (yesterday to the days ahead): made at each gateway's
start on a copy, they cost the server 0.6 s of CPU (their DDL), against 0.1 s for the rest of
its start.

The chain itself stays tested where it is the subject (tests/test_vehicles_migration.py,
tests/test_partitions.py, every gateway started on an empty database) and here: the template
is made by `upgrade_engine`, and the engine fixture runs `upgrade_engine` again on the copy,
which finds it at the head revision."""

from __future__ import annotations

import contextlib
import os
import shutil
import threading
import uuid
from collections.abc import Iterator
from pathlib import Path

from sqlalchemy import Engine, text
from sqlalchemy.engine import make_url

from eqgw.config import RetentionSettings
from eqgw.store.engine import create_engine
from eqgw.store.migrate import upgrade_engine
from eqgw.store.partition_keeper import PartitionKeeper
from eqgw.supervisor import Supervisor

_lock = threading.Lock()
_template: Path | None = None


def copy_migrated_sqlite(target: Path, scratch: Path) -> None:
    """Make `target` (an SQLite file not written yet) a copy of a freshly migrated database,
    migrated into `scratch` (a folder that outlives the test) the first time."""
    global _template
    if target.exists() and target.stat().st_size > 0:
        raise AssertionError(f"{target} is not empty: a migrated copy would overwrite it")
    with _lock:
        if _template is None:
            path = scratch / "eqgw.db"
            engine = create_engine(f"sqlite:///{path}")
            try:
                upgrade_engine(engine)
            finally:
                engine.dispose()  # the last connection checkpoints the WAL into the file
            _template = path
    # shutil.copy keeps the file's mode: the gateway makes its database private (0600).
    shutil.copy(_template, target)


_TEMPLATE_PREFIX = "eqgw_template_"
_pg_template: str | None = None


@contextlib.contextmanager
def migrated_pg_database(admin_url: str) -> Iterator[str]:
    """The URL of a new PostgreSQL database at the head revision on the server of `admin_url`
    (a URL of a database there, without options), dropped afterwards. It is a copy of a
    template migrated the first time in this process (dropped by `drop_pg_template`)."""
    global _pg_template
    admin = create_engine(admin_url, isolation_level="AUTOCOMMIT")
    try:
        with _lock:
            if _pg_template is None:
                _drop_orphaned_templates(admin)
                name = f"{_TEMPLATE_PREFIX}{os.getpid()}_{uuid.uuid4().hex[:6]}"
                _create(admin, name)
                engine = create_engine(_database_url(admin_url, name))
                try:
                    upgrade_engine(engine)
                    # And the time partitions a gateway's first round makes (from yesterday
                    # to the days ahead): DDL of 0.6 s of the server's CPU a database,
                    # made once here instead of at each gateway's start.
                    PartitionKeeper(engine, RetentionSettings(), Supervisor()).round()
                finally:
                    engine.dispose()  # a template must have no session when it is copied
                _pg_template = name
        name = f"t_{uuid.uuid4().hex[:12]}"
        # WAL_LOG (the default) copies block by block through the WAL, no checkpoint.
        _create(admin, name, f'TEMPLATE "{_pg_template}" STRATEGY WAL_LOG')
        try:
            yield _database_url(admin_url, name)
        finally:
            _drop(admin, name)
    finally:
        admin.dispose()


def drop_pg_template(admin_url: str) -> None:
    """Drop this process's template database, if it made one."""
    global _pg_template
    if _pg_template is None:
        return
    admin = create_engine(admin_url, isolation_level="AUTOCOMMIT")
    try:
        _drop(admin, _pg_template)
        _pg_template = None
    finally:
        admin.dispose()


def _drop_orphaned_templates(admin: Engine) -> None:
    """Drop the templates of test processes of this machine that ended without dropping
    theirs (killed)."""
    with admin.connect() as conn:
        names = conn.execute(
            text("SELECT datname FROM pg_database WHERE datname LIKE :p"),
            {"p": f"{_TEMPLATE_PREFIX}%"},
        ).scalars()
        orphans = [
            name
            for name in names
            if (pid := name.removeprefix(_TEMPLATE_PREFIX).split("_")[0]).isdigit()
            and not Path(f"/proc/{pid}").exists()
        ]
    for name in orphans:
        _drop(admin, name)


def _create(admin: Engine, name: str, options: str = "") -> None:
    with admin.connect() as conn:
        conn.execute(text(f'CREATE DATABASE "{name}" {options}'))


def _drop(admin: Engine, name: str) -> None:
    # FORCE: a session a test left behind (a killed gateway's) does not keep the database.
    with admin.connect() as conn:
        conn.execute(text(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)'))


def _database_url(admin_url: str, name: str) -> str:
    return make_url(admin_url).set(database=name).render_as_string(hide_password=False)
