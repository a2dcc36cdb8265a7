"""An SQLite database migrated once per test process and copied into each test's own file.

A migration of an empty SQLite file takes 0.1 s of CPU and 0.3-0.7 s in all (its commits wait
for the disk); a copy takes a millisecond. On PostgreSQL the server's own work dominates (DDL
of ~50 tables and their partitions, 0.2 s of the server's CPU and 0.1 s of the client's;
replaying a dump of a migrated schema took as long): there the copy is a database made from a
migrated template database (`CREATE DATABASE ... TEMPLATE`, which copies its files: 0.1-0.3 s
of the server's CPU, most of it the kernel's), one template per test process. The template also
holds the time partitions a gateway's first maintenance round makes (yesterday to the days
ahead): made at each gateway's start on a copy, they cost the server 0.6 s of CPU (their DDL),
against 0.1 s for the rest of its start.

A copy is made once per test process and used again: when a test is done with it, the sessions
it left are ended and, if its schema is still the template's (a digest of the catalogs), every
table that has a row is emptied and the template's rows and sequence values are put back
(`_reset`: 0.01-0.02 s of the server's CPU, against 0.13 s for a copy and, for its drop, a
checkpoint: PostgreSQL 15 forces one at each DROP DATABASE). A copy whose schema a test changed
(a partition dropped, a table added) is dropped and the next test gets a new one.

The chain itself stays tested where it is the subject (tests/test_vehicles_migration.py,
tests/test_partitions.py, every gateway started on an empty database) and here: the template
is made by `upgrade_engine`, and the engine fixture runs `upgrade_engine` again on the copy,
which finds it at the head revision."""

from __future__ import annotations

import contextlib
import os
import shutil
import threading
import time
import uuid
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import sqlalchemy
from sqlalchemy import Connection, Engine, text
from sqlalchemy.engine import make_url
from sqlalchemy.exc import SQLAlchemyError
from sqlalchemy.pool import NullPool

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
_POOL_PREFIX = "eqgw_copy_"
_pg_template: str | None = None
_pg_template_state: _State | None = None
# Copies a test has finished with and that were reset to the template's state (`_reset`).
_pg_pool: list[str] = []
_pg_copies: set[str] = set()  # every copy this process made and has not dropped


@contextlib.contextmanager
def migrated_pg_database(admin_url: str) -> Iterator[str]:
    """The URL of a PostgreSQL database at the head revision on the server of `admin_url`
    (a URL of a database there, without options), with nothing in it but what the migrations
    and a gateway's first round put there. It is a copy of a template migrated the first
    time in this process, or a copy an earlier test had and that was then reset to the
    template's state; one whose reset cannot be shown complete is dropped. The copies and the
    template are dropped by `drop_pg_template`."""
    global _pg_template, _pg_template_state
    admin = _admin(admin_url)
    try:
        with _lock:
            if _pg_template is None:
                _drop_orphans(admin)
                name = f"{_TEMPLATE_PREFIX}{os.getpid()}_{uuid.uuid4().hex[:6]}"
                _create(admin, name)
                engine = create_engine(_database_url(admin_url, name))
                try:
                    upgrade_engine(engine)
                    # And the time partitions a gateway's first round makes (from yesterday
                    # to the days ahead): DDL of 0.6 s of the server's CPU a database,
                    # made once here instead of at each gateway's start.
                    PartitionKeeper(engine, RetentionSettings(), Supervisor()).round()
                    _pg_template_state = _State.of(engine)
                finally:
                    engine.dispose()  # a template must have no session when it is copied
                _pg_template = name
            name = _pg_pool.pop() if _pg_pool else ""
        if not name:
            name = f"{_POOL_PREFIX}{os.getpid()}_{uuid.uuid4().hex[:8]}"
            # WAL_LOG (the default) copies block by block through the WAL, no checkpoint.
            _create(admin, name, f'TEMPLATE "{_pg_template}" STRATEGY WAL_LOG')
            _pg_copies.add(name)
        url = _database_url(admin_url, name)
        yield url
        if _reset(admin, url, name):
            with _lock:
                _pg_pool.append(name)
        else:
            _drop(admin, name)
            _pg_copies.discard(name)
    finally:
        admin.dispose()


@dataclass(frozen=True)
class _State:
    """What a copy must be to be given to another test: the template's schema (a digest of
    its catalogs), the values of its sequences, and the rows of its tables that have any."""

    schema: str
    sequences: dict[str, tuple[int, bool]]
    rows: dict[str, str]  # table -> its rows (a JSON array), for each table that has any

    @classmethod
    def of(cls, engine: Engine) -> _State:
        with engine.connect() as conn:
            tables = conn.execute(text(_TABLES)).scalars().all()
            rows = {}
            for table in tables:
                found = conn.execute(
                    text(f"SELECT CAST(jsonb_agg(t ORDER BY t::text) AS text) FROM {table} t")
                ).scalar()
                if found is not None:
                    rows[table] = found
            schema = conn.execute(text(_SCHEMA_DIGEST)).scalar_one()
            return cls(schema=schema, sequences=_sequences(conn), rows=rows)


# Every table with storage outside the system's schemas (partitions included), quoted.
_TABLES = """
SELECT format('%I.%I', n.nspname, c.relname) FROM pg_class c
JOIN pg_namespace n ON n.oid = c.relnamespace
WHERE c.relkind = 'r' AND n.nspname NOT IN ('pg_catalog', 'information_schema')
  AND n.nspname NOT LIKE 'pg\\_%'
ORDER BY 1
"""
# A digest of everything a test could change in a database's schema that the reset does not
# put back: relations (partitions included) and their columns, defaults, constraints,
# triggers, rules, policies, functions, schemas and their privileges, the database's own
# settings, and what must not outlive a test (prepared transactions, large objects).
_SCHEMA_DIGEST = """
WITH ns AS (
  SELECT oid, nspname, nspacl FROM pg_namespace
  WHERE nspname NOT IN ('pg_catalog', 'information_schema') AND nspname NOT LIKE 'pg\\_%'
), parts AS (
  SELECT 'n' || nspname || coalesce(nspacl::text, '') AS s FROM ns
  UNION ALL
  SELECT format('c %s %s %s %s %s %s %s', n.nspname, c.relname, c.relkind, c.relpersistence,
                c.relacl, c.relrowsecurity, pg_get_expr(c.relpartbound, c.oid))
  FROM pg_class c JOIN ns n ON n.oid = c.relnamespace
  UNION ALL
  SELECT format('a %s %s %s %s %s %s', a.attrelid::regclass, a.attname, a.atttypid::regtype,
                a.attnotnull, a.attisdropped, pg_get_expr(d.adbin, d.adrelid))
  FROM pg_attribute a JOIN pg_class c ON c.oid = a.attrelid JOIN ns ON ns.oid = c.relnamespace
  LEFT JOIN pg_attrdef d ON d.adrelid = a.attrelid AND d.adnum = a.attnum
  WHERE a.attnum > 0
  UNION ALL
  SELECT format('k %s %s %s', conrelid::regclass, conname, pg_get_constraintdef(oid))
  FROM pg_constraint WHERE connamespace IN (SELECT oid FROM ns)
  UNION ALL
  SELECT format('t %s %s %s', tgrelid::regclass, tgname, tgenabled) FROM pg_trigger
  WHERE NOT tgisinternal
    AND tgrelid IN (SELECT c.oid FROM pg_class c JOIN ns ON ns.oid = c.relnamespace)
  UNION ALL
  SELECT format('r %s %s', ev_class::regclass, rulename) FROM pg_rewrite
  WHERE ev_class IN (SELECT c.oid FROM pg_class c JOIN ns ON ns.oid = c.relnamespace)
  UNION ALL
  SELECT format('p %s %s', polrelid::regclass, polname) FROM pg_policy
  UNION ALL
  SELECT format('f %s %s %s', pronamespace::regnamespace, proname, md5(prosrc)) FROM pg_proc
  WHERE pronamespace IN (SELECT oid FROM ns)
  UNION ALL
  SELECT format('s %s', setconfig) FROM pg_db_role_setting s
  JOIN pg_database d ON d.oid = s.setdatabase WHERE d.datname = current_database()
  UNION ALL
  SELECT format('x %s', gid) FROM pg_prepared_xacts WHERE database = current_database()
  UNION ALL
  SELECT format('l %s', oid) FROM pg_largeobject_metadata
)
SELECT md5(string_agg(s, E'\\n' ORDER BY s)) FROM parts
"""


def _sequences(conn: Connection) -> dict[str, tuple[int, bool]]:
    """Each sequence's state (last value, whether it was used), in two round trips."""
    names = (
        conn.execute(
            text(
                "SELECT format('%I.%I', schemaname, sequencename) FROM pg_sequences "
                "WHERE schemaname NOT LIKE 'pg\\_%' ORDER BY 1"
            )
        )
        .scalars()
        .all()
    )
    if not names:
        return {}
    each = " UNION ALL ".join(
        f"SELECT {i}, last_value, is_called FROM {name}" for i, name in enumerate(names)
    )
    return {names[i]: (last, called) for i, last, called in conn.execute(text(each))}


def _reset(admin: Engine, url: str, name: str) -> bool:
    """Put a copy a test had back into the template's state: end the sessions the test left,
    check that its schema is the template's, empty every table that has a row (TRUNCATE: new
    files, no dead rows for the next test), and put the template's rows and sequence values
    back. False when the copy is not the template's (it is then dropped, not reused)."""
    state = _pg_template_state
    assert state is not None
    with admin.connect() as conn:
        # What a test left connected (a killed gateway's sessions), as DROP ... FORCE did.
        conn.execute(
            text(
                "SELECT pg_terminate_backend(pid) FROM pg_stat_activity "
                "WHERE datname = :name AND pid <> pg_backend_pid()"
            ),
            {"name": name},
        )
        for _ in range(100):  # a terminated session ends within milliseconds
            left = conn.execute(
                text("SELECT count(*) FROM pg_stat_activity WHERE datname = :name"),
                {"name": name},
            ).scalar_one()
            if not left:
                break
            time.sleep(0.02)
        else:
            return False
    engine = create_engine(url)
    try:
        with engine.begin() as conn:
            conn.execute(text("SET LOCAL lock_timeout = '2s'"))
            if conn.execute(text(_SCHEMA_DIGEST)).scalar_one() != state.schema:
                return False
            # Each table that has a row, or rows other than the template's.
            tables = conn.execute(text(_TABLES)).scalars().all()
            changed = " UNION ALL ".join(
                f"SELECT {i} WHERE (SELECT jsonb_agg(t ORDER BY t::text) FROM {table} t) "
                f"IS DISTINCT FROM CAST(:r{i} AS jsonb)"
                if table in state.rows
                else f"SELECT {i} WHERE EXISTS (SELECT FROM {table})"
                for i, table in enumerate(tables)
            )
            rows = {f"r{tables.index(table)}": v for table, v in state.rows.items()}
            emptied = [tables[i] for i in conn.execute(text(changed), rows).scalars()]
            if emptied:  # CASCADE: with the tables that refer to them (empty or not)
                conn.execute(text(f"TRUNCATE {', '.join(emptied)} CASCADE"))
            for table, rows_json in state.rows.items():
                conn.execute(
                    text(
                        f"INSERT INTO {table} SELECT * FROM "
                        f"jsonb_populate_recordset(NULL::{table}, CAST(:rows AS jsonb)) "
                        f"WHERE NOT EXISTS (SELECT FROM {table})"
                    ),
                    {"rows": rows_json},
                )
            current = _sequences(conn)
            for seq, (last, called) in state.sequences.items():
                if current.get(seq) != (last, called):
                    conn.execute(
                        text("SELECT setval(:seq, :last, :called)"),
                        {"seq": seq, "last": last, "called": called},
                    )
        return True
    except SQLAlchemyError:  # a lock not granted in 2 s, a session back: a new copy instead
        return False
    finally:
        engine.dispose()


def drop_pg_template(admin_url: str) -> None:
    """Drop this process's copies and template database, if it made them."""
    global _pg_template
    admin = _admin(admin_url)
    try:
        for name in sorted(_pg_copies):
            _drop(admin, name)
        _pg_copies.clear()
        _pg_pool.clear()
        if _pg_template is not None:
            _drop(admin, _pg_template)
            _pg_template = None
    finally:
        admin.dispose()


def _drop_orphans(admin: Engine) -> None:
    """Drop the templates and copies of test processes of this machine that ended without
    dropping theirs (killed)."""
    with admin.connect() as conn:
        names = conn.execute(
            text("SELECT datname FROM pg_database WHERE datname LIKE :t OR datname LIKE :c"),
            {"t": f"{_TEMPLATE_PREFIX}%", "c": f"{_POOL_PREFIX}%"},
        ).scalars()
        orphans = [
            name
            for name in names
            if (pid := name.split("_")[2]).isdigit() and not Path(f"/proc/{pid}").exists()
        ]
    for name in orphans:
        _drop(admin, name)


def _admin(admin_url: str) -> Engine:
    """An engine for CREATE and DROP DATABASE: SQLAlchemy's own, without eqgw's statement,
    lock and answer timeouts. On PostgreSQL 15 a DROP DATABASE waits for a checkpoint it
    forces, which writes and syncs everything the run changed since the last one: over 10 s
    seen under a full run's load."""
    return sqlalchemy.create_engine(admin_url, isolation_level="AUTOCOMMIT", poolclass=NullPool)


def _create(admin: Engine, name: str, options: str = "") -> None:
    with admin.connect() as conn:
        conn.execute(text(f'CREATE DATABASE "{name}" {options}'))


def _drop(admin: Engine, name: str) -> None:
    # FORCE: a session a test left behind (a killed gateway's) does not keep the database.
    with admin.connect() as conn:
        conn.execute(text(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)'))


def _database_url(admin_url: str, name: str) -> str:
    return make_url(admin_url).set(database=name).render_as_string(hide_password=False)
