"""Engines for SQLite (WAL) and PostgreSQL from one database URL, sync and async."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from sqlalchemy import Engine, event
from sqlalchemy import create_engine as sa_create_engine
from sqlalchemy.engine import URL, make_url
from sqlalchemy.exc import ArgumentError

from app.store.errors import DatabaseUrlError, StoreError

if TYPE_CHECKING:
    from sqlalchemy.ext.asyncio import AsyncEngine

# A writer waits this long for another process's SQLite write lock before it counts a failure.
SQLITE_BUSY_TIMEOUT_MS = 10_000

_SYNC_PG_DRIVERS = {"psycopg", "psycopg2", "pg8000"}
_ASYNC_PG_DRIVERS = {"asyncpg", "psycopg", "psycopg_async"}


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
            f"unsupported database {backend!r}: use sqlite:///FILE or postgresql+asyncpg://..."
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


def async_url(url: str | URL) -> URL:
    """The URL with an asyncio driver: aiosqlite, or asyncpg unless psycopg was asked for."""
    parsed = parse_url(url)
    if parsed.get_backend_name() == "sqlite":
        return parsed.set(drivername="sqlite+aiosqlite")
    driver = parsed.get_driver_name()
    if driver not in _ASYNC_PG_DRIVERS:
        driver = "asyncpg"
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


def _pg_connect_args_for_asyncpg(url: URL) -> tuple[URL, dict[str, Any]]:
    """Move libpq's `options=-csearch_path=...` into asyncpg's server_settings."""
    options = url.query.get("options")
    if not options:
        return url, {}
    opts = options if isinstance(options, str) else " ".join(options)
    settings: dict[str, str] = {}
    for part in opts.split():
        if part.startswith("-c") and "=" in part:
            key, _, value = part[2:].partition("=")
            settings[key] = value
    return url.difference_update_query(["options"]), {"server_settings": settings}


def create_engine(url: str | URL, **kwargs: Any) -> Engine:
    """A synchronous engine (used by the writer thread, migrations and queries)."""
    target = sync_url(url)
    if target.get_backend_name() == "sqlite":
        engine = sa_create_engine(target, **kwargs)
        _install_sqlite_pragmas(engine)
        return engine
    kwargs.setdefault("pool_pre_ping", True)  # a restarted server leaves dead pooled conns
    return sa_create_engine(target, **kwargs)


def create_async_engine(url: str | URL, **kwargs: Any) -> AsyncEngine:
    """An asyncio engine for request handlers; same pragmas and schema as the sync one."""
    try:
        # Imported here: SQLAlchemy's asyncio layer needs greenlet, which the ingest does not.
        from sqlalchemy.ext.asyncio import create_async_engine as sa_create_async_engine
    except ImportError as exc:
        raise StoreError(f"async engines are unavailable: {exc}") from exc
    target = async_url(url)
    if target.get_backend_name() == "sqlite":
        engine = sa_create_async_engine(target, **kwargs)
        _install_sqlite_pragmas(engine.sync_engine)
        return engine
    kwargs.setdefault("pool_pre_ping", True)
    if target.get_driver_name() == "asyncpg":
        target, extra = _pg_connect_args_for_asyncpg(target)
        if extra:
            kwargs.setdefault("connect_args", {}).update(extra)
    return sa_create_async_engine(target, **kwargs)
