"""A gateway's engine is disposed when it stops, and a thread may still hold one of its
connections then (a query the stop did not wait for). That connection, returned afterwards,
is closed at once: never left open in a pool nothing uses any more (a server connection held
until the collector finds it, and a ResourceWarning then, in whatever runs at that moment)."""

from __future__ import annotations

import gc
import sqlite3
import threading
import warnings

import psycopg
from sqlalchemy import event, text

from eqgw.store.engine import create_engine


def _closed(raw: object) -> bool:
    if isinstance(raw, psycopg.Connection):
        return raw.closed
    assert isinstance(raw, sqlite3.Connection), type(raw)
    try:
        raw.execute("SELECT 1")
    except sqlite3.ProgrammingError:
        return True
    return False


def test_a_connection_returned_after_dispose_is_closed(db_url: str) -> None:
    engine = create_engine(db_url)
    held = threading.Event()
    release = threading.Event()
    raws: list[object] = []

    def query() -> None:  # a query in a thread, still running when the gateway stops
        with engine.connect() as conn:
            conn.execute(text("SELECT 1"))
            raws.append(conn.connection.dbapi_connection)
            held.set()
            release.wait(10)

    worker = threading.Thread(target=query)
    worker.start()
    assert held.wait(10)
    with engine.connect() as conn:  # an idle pooled connection too
        conn.execute(text("SELECT 1"))
        idle = conn.connection.dbapi_connection
    assert idle is not raws[0]
    engine.dispose()
    assert _closed(idle)  # checked in: closed by the dispose itself
    assert not _closed(raws[0])  # still in use: the thread's query goes on
    release.set()
    worker.join(10)
    assert _closed(raws[0])  # returned after the dispose: closed then
    with warnings.catch_warnings():
        warnings.simplefilter("error", ResourceWarning)
        del raws[:]
        gc.collect()
    engine.dispose()


def test_an_engine_disposed_again_still_serves(db_url: str) -> None:
    """Dispose is also the way to drop dead connections (a restarted server): the engine
    goes on with a new pool, and its connections stay open between uses."""
    engine = create_engine(db_url)
    try:
        with engine.connect() as conn:
            conn.execute(text("SELECT 1"))
        engine.dispose()
        with engine.connect() as conn:
            raw = conn.connection.dbapi_connection
            assert conn.execute(text("SELECT 1")).scalar() == 1
        assert not _closed(raw)  # the new pool keeps it for the next use
    finally:
        engine.dispose()


def test_a_connection_opened_while_the_engine_is_disposed_is_closed_when_returned(
    db_url: str,
) -> None:
    """A thread asks the pool for a connection just before the stop disposes of the engine,
    and the connection is made after it (a new connection takes its time: a loaded machine, a
    slow server). It belongs to the pool the dispose replaced: returned, it is closed too."""
    engine = create_engine(db_url)
    connecting = threading.Event()
    disposed = threading.Event()
    raws: list[object] = []

    @event.listens_for(engine, "connect", insert=True)
    def _slow_connect(*_: object) -> None:  # first of the new connection's set-up
        connecting.set()
        assert disposed.wait(10)

    def query() -> None:  # e.g. a retention prune the stop did not wait for
        with engine.connect() as conn:
            conn.execute(text("SELECT 1"))
            raws.append(conn.connection.dbapi_connection)

    worker = threading.Thread(target=query)
    worker.start()
    assert connecting.wait(10)
    engine.dispose()
    disposed.set()
    worker.join(10)
    assert not worker.is_alive() and raws
    assert _closed(raws[0])  # returned to the replaced pool: closed, not left open there
    with warnings.catch_warnings():
        warnings.simplefilter("error", ResourceWarning)
        del raws[:]
        gc.collect()
    engine.dispose()
