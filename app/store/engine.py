"""Engines for SQLite (WAL) and PostgreSQL from one database URL.

Every engine is synchronous (pysqlite, psycopg 3): the ingest writes from its own thread and
the API runs its queries in worker threads. URLs naming an asyncio driver
(`postgresql+asyncpg://`, `sqlite+aiosqlite://`) are accepted and mapped to these.
"""

from __future__ import annotations

import os
from typing import Any

from sqlalchemy import Engine, event
from sqlalchemy import create_engine as sa_create_engine
from sqlalchemy.engine import URL, make_url
from sqlalchemy.exc import ArgumentError

from eqgw.files import create_private_file
from eqgw.store.errors import DatabaseUrlError

# A writer waits this long for another process's SQLite write lock before it counts a failure.
SQLITE_BUSY_TIMEOUT_MS = 10_000

_SYNC_PG_DRIVERS = {"psycopg", "psycopg2", "pg8000"}


def parse_url(url: str | URL) -> URL:
    """Parse a database URL, raising DatabaseUrlError for anything but SQLite or PostgreSQL."""
    try:
        parsed = make_url(url)
    except ArgumentError as exc:
        raise DatabaseUrlError(f"not a database URL: {url!r}") from exc
    backend = parsed.get_backend_name()
    if backend == "postgres":  # Heroku-style scheme
        parsed = parsed.set(drivername="postgresql")
        backend = "postgresql"
    if backend not in ("sqlite", "postgresql"):
        raise DatabaseUrlError(
            f"unsupported database {backend!r}: use sqlite:///FILE or postgresql://..."
        )
    return parsed


def is_sqlite(url: str | URL) -> bool:
    """Whether the URL names an SQLite database."""
    return parse_url(url).get_backend_name() == "sqlite"


def sync_url(url: str | URL) -> URL:
    """The URL with a synchronous driver: pysqlite, or psycopg 3 for any PostgreSQL URL."""
    parsed = parse_url(url)
    if parsed.get_backend_name() == "sqlite":
        return parsed.set(drivername="sqlite")
    driver = parsed.get_driver_name()
    # asyncpg URLs are accepted everywhere; the writer thread runs them through psycopg 3.
    if driver not in _SYNC_PG_DRIVERS or driver == "psycopg2":
        driver = "psycopg"
    return parsed.set(drivername=f"postgresql+{driver}")


def _install_sqlite_pragmas(engine: Engine) -> None:
    """WAL, busy timeout and explicit BEGIN on every pooled SQLite connection."""

    @event.listens_for(engine, "connect")
    def _on_connect(dbapi_conn: Any, _record: Any) -> None:
        # Let SQLAlchemy, not the sqlite3 module, decide when transactions begin.
        dbapi_conn.isolation_level = None
        cur = dbapi_conn.cursor()
        try:
            cur.execute("PRAGMA journal_mode=WAL")
            cur.execute(f"PRAGMA busy_timeout={SQLITE_BUSY_TIMEOUT_MS}")
            # NORMAL is durable against crashes in WAL mode; only a power cut can lose the
            # last commits, which the gateway accepts for 2-3x faster commits.
            cur.execute("PRAGMA synchronous=NORMAL")
            cur.execute("PRAGMA foreign_keys=ON")
        finally:
            cur.close()

    @event.listens_for(engine, "begin")
    def _on_begin(conn: Any) -> None:
        # Writers take the write lock up front: a deferred transaction that upgrades later
        # fails with SQLITE_BUSY at once instead of honouring busy_timeout.
        mode = conn.get_execution_options().get("sqlite_begin", "DEFERRED")
        conn.exec_driver_sql(f"BEGIN {mode}")


def _sqlite_file(url: URL) -> str | None:
    """The file of an SQLite URL, or None for an in-memory database."""
    db = url.database
    if not db or db == ":memory:" or db.startswith("file:") or url.query.get("mode") == "memory":
        return None
    return db


def create_engine(url: str | URL, **kwargs: Any) -> Engine:
    """A synchronous engine (used by the writer thread, migrations and queries)."""
    target = sync_url(url)
    if target.get_backend_name() == "sqlite":
        path = _sqlite_file(target)
        if path is not None and os.path.isdir(os.path.dirname(os.path.abspath(path))):
            create_private_file(path)
        engine = sa_create_engine(target, **kwargs)
        _install_sqlite_pragmas(engine)
        return engine
    kwargs.setdefault("pool_pre_ping", True)  # a restarted server leaves dead pooled conns
    return sa_create_engine(target, **kwargs)
