"""Engines for SQLite (WAL) and PostgreSQL from one database URL.

Every engine is synchronous (pysqlite, psycopg 3): the ingest writes from its own thread and
the API runs its queries in worker threads. URLs naming an asyncio driver
(`postgresql+asyncpg://`, `sqlite+aiosqlite://`) are accepted and mapped to these.
"""

from __future__ import annotations

import contextlib
import math
import os
import sqlite3
import threading
import time
import weakref
from collections.abc import Iterator
from contextvars import ContextVar
from typing import TYPE_CHECKING, TypedDict, TypeVar, Unpack

import psycopg
from psycopg.abc import ConnParam, PQGen
from psycopg.adapt import AdaptersMap
from psycopg.conninfo import make_conninfo
from psycopg.rows import TupleRow
from sqlalchemy import Connection, Engine, Pool, event
from sqlalchemy import create_engine as sa_create_engine
from sqlalchemy.engine import URL, make_url
from sqlalchemy.engine.interfaces import DBAPIConnection, IsolationLevel
from sqlalchemy.exc import ArgumentError
from sqlalchemy.pool import ConnectionPoolEntry

from eqgw.files import create_private_file
from eqgw.store.errors import DatabaseUrlError

if TYPE_CHECKING:
    from eqgw.config import DatabaseSettings

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


_POOL_GENERATION = "eqgw_pool_generation"


def _close_returns_after_dispose(engine: Engine) -> None:
    """A connection returned to a pool the engine has disposed of is closed at once.

    `Engine.dispose` closes the connections in its pool, not those checked out: a query in a
    thread the stop did not wait for. Returned afterwards, such a connection would stay open
    in a pool nothing refers to (a server connection held until the collector finds it)."""
    generation = [0]

    @event.listens_for(engine, "engine_disposed")
    def _disposed(_engine: Engine) -> None:
        generation[0] += 1

    # Tagged when the connection starts being made, not once made: a connection made while
    # the engine is disposed (a thread asked the old pool for one just before) belongs to
    # the old pool, and is closed when returned. Registered before any other `do_connect`
    # listener (the first to return a connection ends the chain).
    @event.listens_for(engine, "do_connect")
    def _tag(_dialect: object, record: ConnectionPoolEntry, *_: object) -> None:
        record.info[_POOL_GENERATION] = generation[0]

    @event.listens_for(engine, "checkin")
    def _checkin(dbapi_conn: DBAPIConnection | None, record: ConnectionPoolEntry) -> None:
        if dbapi_conn is not None and record.info.get(_POOL_GENERATION) != generation[0]:
            with contextlib.suppress(Exception):
                dbapi_conn.close()


def _install_sqlite_pragmas(engine: Engine) -> None:
    """WAL, busy timeout and explicit BEGIN on every pooled SQLite connection."""

    @event.listens_for(engine, "connect")
    def _on_connect(dbapi_conn: DBAPIConnection, _record: object) -> None:
        if not isinstance(dbapi_conn, sqlite3.Connection):  # pysqlite's, always
            raise TypeError(f"not an SQLite connection: {dbapi_conn!r}")
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
    def _on_begin(conn: Connection) -> None:
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


# -- deadlines ---------------------------------------------------------------------------------
# The monotonic time by which the database work of the current context (a request, a writer's
# batch, a shutdown) must be over; math.inf: no deadline at all (migrations). Unset: each
# operation gets its connection's `answer_timeout_s`. A context variable: asyncio.to_thread
# carries it into the worker thread that runs the query.
_deadline: ContextVar[float | None] = ContextVar("eqgw_db_deadline", default=None)


class DatabaseDeadline(psycopg.OperationalError):
    """The database did not answer in time; the connection was closed (SQLAlchemy discards
    it), so the caller sees an outage, never a hang."""


@contextlib.contextmanager
def db_deadline(seconds: float | None) -> Iterator[None]:
    """Database work inside ends within `seconds` (None: no deadline at all), or sooner if an
    enclosing deadline says so."""
    end = math.inf if seconds is None else time.monotonic() + seconds
    outer = _deadline.get()
    if outer is not None and seconds is not None:
        end = min(end, outer)
    token = _deadline.set(end)
    try:
        yield
    finally:
        _deadline.reset(token)


def db_deadline_at(end: float) -> contextlib.AbstractContextManager[None]:
    """`db_deadline` to a monotonic time."""
    return db_deadline(end - time.monotonic())


@contextlib.contextmanager
def database_deadline_scope() -> Iterator[None]:
    """Whatever deadline the work inside sets for its context (`end_database_work_by`,
    `restart_deadline`) is undone on leaving it."""
    token = _deadline.set(_deadline.get())
    try:
        yield
    finally:
        _deadline.reset(token)


def end_database_work_by(end: float) -> None:
    """From here on in the current context (a task, and the threads it starts), database
    work ends by the monotonic time `end` (a shutdown: nothing after it may hang)."""
    _deadline.set(end)


def restart_deadline(seconds: float) -> None:
    """The current context's database deadline, from now (a request whose body just
    arrived: the time its client took to send it is not the database's)."""
    _deadline.set(time.monotonic() + seconds)


def deadline_left() -> float | None:
    """Seconds left before the current context's database deadline (None: none set)."""
    end = _deadline.get()
    if end is None or end == math.inf:
        return None
    return max(0.0, end - time.monotonic())


def _limit(default: float | None) -> float | None:
    """Seconds the next operation may wait, or None (no limit); raises past the deadline."""
    end = _deadline.get()
    if end is None:
        return default
    if end == math.inf:
        return None
    left = end - time.monotonic()
    if left <= 0:
        raise DatabaseDeadline("database deadline passed")
    return left if default is None else min(left, default)


_RV = TypeVar("_RV")


class DeadlineConnection(psycopg.Connection[TupleRow]):
    """A psycopg connection whose every wait for the server (a statement, a fetch, a commit,
    a pipeline of inserts) ends by its deadline: past it the connection is closed and the
    operation fails. Works whatever the network does (TCP keepalive and tcp_user_timeout do
    not fire on a path where a proxy or firewall keeps the socket alive and drops the data)."""

    answer_timeout_s: float | None = None

    def wait(self, gen: PQGen[_RV], interval: float = 0.1, timeout: float | None = None) -> _RV:
        health = _CONN_HEALTH.get(self)
        if health is not None and health.down():
            # Connections to it failed moments ago: fail at once rather than tie up a
            # thread for the whole deadline (one caller probes again once `hold_s` passed).
            with contextlib.suppress(Exception):
                self.pgconn.finish()
            raise DatabaseDeadline("the database did not answer moments ago")
        limit = _limit(self.answer_timeout_s)
        mine = limit is not None and (timeout is None or limit < timeout)
        if mine:
            timeout = limit
        try:
            result = super().wait(gen, interval, timeout)
        except psycopg.OperationalError as exc:
            if not mine or type(exc).__name__ != "_WaitTimeout":
                raise
            with contextlib.suppress(Exception):
                self.pgconn.finish()  # its state is unknown: never used again
            raise DatabaseDeadline(
                f"the database did not answer within {timeout:.1f} s (connection closed)"
            ) from None
        if health is not None:
            health.ok()
        return result


class DbHealth:
    """Whether the database failed lately: while `down()`, callers with an answer in memory
    give it at once instead of waiting for a database that just did not answer."""

    def __init__(self, hold_s: float = 5.0) -> None:
        self.hold_s = hold_s
        self._until = 0.0
        self._lock = threading.Lock()

    def failed(self) -> None:
        with self._lock:
            self._until = time.monotonic() + self.hold_s

    def ok(self) -> None:
        if self._until:
            self._until = 0.0

    def down(self) -> bool:
        return time.monotonic() < self._until


_HEALTH: weakref.WeakKeyDictionary[Engine, DbHealth] = weakref.WeakKeyDictionary()
_CONN_HEALTH: weakref.WeakKeyDictionary[DeadlineConnection, DbHealth] = weakref.WeakKeyDictionary()


def health_of(engine: Engine) -> DbHealth:
    """The database health of an engine (one per engine)."""
    h = _HEALTH.get(engine)
    if h is None:
        h = _HEALTH[engine] = DbHealth()
    return h


def unavailable_error() -> Exception:
    """What a caller raises instead of asking a database that failed moments ago."""
    from sqlalchemy.exc import OperationalError

    return OperationalError(None, None, DatabaseDeadline("the database did not answer moments ago"))


def _ms(seconds: float) -> int:
    return max(1, int(seconds * 1000))


def _pg_connect_args(db: DatabaseSettings) -> dict[str, ConnParam]:
    ms = _ms
    options = (
        f"-c statement_timeout={ms(db.statement_timeout_s)} "
        f"-c lock_timeout={ms(db.lock_timeout_s)} "
        f"-c idle_in_transaction_session_timeout={ms(db.idle_in_transaction_s)}"
    )
    return {
        "connect_timeout": db.connect_timeout_s,
        "keepalives": 1,
        "keepalives_idle": db.keepalive_idle_s,
        "keepalives_interval": db.keepalive_interval_s,
        "keepalives_count": db.keepalive_count,
        "tcp_user_timeout": ms(db.tcp_user_timeout_s),
        "options": options,
    }


class _ConnectOptions(TypedDict, total=False):
    """The keywords of psycopg.connect that are not connection keywords."""

    autocommit: bool
    prepare_threshold: int | None
    context: AdaptersMap


def _psycopg_options(cparams: dict[str, object]) -> tuple[_ConnectOptions, dict[str, ConnParam]]:
    """SQLAlchemy's keywords for psycopg.connect (the URL's, `connect_args`, the dialect's
    adapters as `context`), split into psycopg's own options and the connection keywords
    (which psycopg turns into text: so does this, for a type other than str and int)."""
    options: _ConnectOptions = {}
    keywords: dict[str, ConnParam] = {}
    for key, value in cparams.items():
        if key == "context" and isinstance(value, AdaptersMap):
            options["context"] = value
        elif key == "autocommit" and isinstance(value, bool):
            options["autocommit"] = value
        elif key == "prepare_threshold" and (value is None or isinstance(value, int)):
            options["prepare_threshold"] = value
        elif value is None or isinstance(value, str | int):
            keywords[key] = value
        else:
            keywords[key] = str(value)
    return options, keywords


def _install_pg_deadlines(engine: Engine, db: DatabaseSettings) -> None:
    extra = _pg_connect_args(db)
    health = health_of(engine)

    @event.listens_for(engine, "do_connect")
    def _connect(
        _dialect: object, _rec: object, cargs: list[object], cparams: dict[str, object]
    ) -> DeadlineConnection:
        options, keywords = _psycopg_options(cparams)
        params = {**keywords, **{k: v for k, v in extra.items() if k != "options"}}
        # The URL may carry options of its own (a schema's search_path): both apply.
        params["options"] = f"{cparams.get('options', '')} {extra['options']}".strip()
        if health.down():
            raise DatabaseDeadline("the database did not answer moments ago")
        left = _limit(float(db.connect_timeout_s))
        if left is not None:
            params["connect_timeout"] = max(2, min(db.connect_timeout_s, math.ceil(left)))
        try:
            conninfo = make_conninfo(str(cargs[0]) if cargs else "", **params)
            conn = DeadlineConnection.connect(conninfo, **options)
        except psycopg.errors.ConnectionTimeout:
            health.failed()  # the server does not answer at all (not: it refused)
            raise
        conn.answer_timeout_s = db.answer_timeout_s
        _CONN_HEALTH[conn] = health
        return conn


class EngineOptions(TypedDict, total=False):
    """What `create_engine` passes on to SQLAlchemy's."""

    connect_args: dict[str, object]
    echo: bool
    isolation_level: IsolationLevel
    max_overflow: int
    poolclass: type[Pool]
    pool_pre_ping: bool
    pool_size: int
    pool_timeout: float


def create_engine(
    url: str | URL, *, deadlines: DatabaseSettings | None = None, **kwargs: Unpack[EngineOptions]
) -> Engine:
    """A synchronous engine (used by the writer thread, migrations and queries). On
    PostgreSQL every operation has a deadline (`deadlines`, the defaults if not given)."""
    target = sync_url(url)
    if target.get_backend_name() == "sqlite":
        path = _sqlite_file(target)
        if path is not None and os.path.isdir(os.path.dirname(os.path.abspath(path))):
            create_private_file(path)
        engine = sa_create_engine(target, **kwargs)
        _install_sqlite_pragmas(engine)
        _close_returns_after_dispose(engine)
        return engine
    from eqgw.config import DatabaseSettings

    db = deadlines or DatabaseSettings()
    kwargs.setdefault("pool_pre_ping", True)  # a restarted server leaves dead pooled conns
    if target.get_driver_name() == "psycopg":
        kwargs.setdefault("pool_timeout", db.pool_timeout_s)
    engine = sa_create_engine(target, **kwargs)
    _close_returns_after_dispose(engine)  # its `do_connect` listener first
    if target.get_driver_name() == "psycopg":
        _install_pg_deadlines(engine, db)
    return engine
