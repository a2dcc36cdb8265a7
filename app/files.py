"""Files the gateway creates that hold its data: private to the owner."""

from __future__ import annotations

import os
import sqlite3


def create_private_file(path: str | os.PathLike[str]) -> None:
    """Create `path` readable and writable by its owner only (0600) unless it exists.

    SQLite creates its -wal and -shm files with the mode of the database file, so a database
    made here first keeps its companions private too (SQLite itself would use 0644).
    """
    try:
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    except FileExistsError:
        return
    os.close(fd)


def open_local_sqlite(path: str | os.PathLike[str]) -> sqlite3.Connection:
    """A gateway-local SQLite file (the forwarder's buffer, the writer's journal), created 0600:
    an autocommit connection (transactions through `ImmediateTransaction`) in WAL mode with
    `synchronous=NORMAL` (a killed process loses nothing committed; a power cut may lose the
    last commits) and a 10 s wait for another connection's lock."""
    create_private_file(path)
    db = sqlite3.connect(path, check_same_thread=False, isolation_level=None)
    try:
        db.execute("PRAGMA journal_mode=WAL")
        db.execute("PRAGMA synchronous=NORMAL")
        db.execute("PRAGMA busy_timeout=10000")
    except BaseException:
        db.close()
        raise
    return db


class ImmediateTransaction:
    """BEGIN IMMEDIATE ... COMMIT (ROLLBACK on an exception) on an autocommit connection."""

    def __init__(self, db: sqlite3.Connection) -> None:
        self._db = db

    def __enter__(self) -> None:
        self._db.execute("BEGIN IMMEDIATE")

    def __exit__(self, exc_type: object, *rest: object) -> None:
        if exc_type is None:
            try:
                self._db.execute("COMMIT")
                return
            except sqlite3.Error:
                self._rollback()  # a COMMIT that failed (SQLITE_FULL) leaves it open
                raise
        self._rollback()

    def _rollback(self) -> None:
        # SQLite may have rolled back already (some errors end the transaction themselves).
        if self._db.in_transaction:
            self._db.execute("ROLLBACK")
