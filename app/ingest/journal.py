"""The writer's journal: rows held while the database is away, spilled to a local SQLite file.

The same mechanism as the forwarder's buffer (app/forward/buffer.py): a SQLite file in WAL mode,
`synchronous=NORMAL` (a killed process loses nothing committed; a power cut may lose the last
commits), entries numbered by AUTOINCREMENT and forgotten by number once the database has them.
An entry is a chunk of writer rows (up to one batch), kept in the order they were accepted.

One file per database (its name carries a hash of the database URL, which the file also
records), so a journal is never replayed into another database. A process holds an exclusive
lock (flock) on the file it uses; a second gateway of the same database in the same folder takes the
next free slot (`...-2.db`, ...), and at start a gateway adopts the entries of slots no running
process holds (a gateway killed and never restarted in this folder).
"""

from __future__ import annotations

import contextlib
import fcntl
import hashlib
import io
import logging
import os
import pickle
import sqlite3
import threading
from collections.abc import Sequence
from pathlib import Path

from sqlalchemy.engine import make_url

from eqgw.files import ImmediateTransaction, open_local_sqlite
from eqgw.ingest.rows import Row, from_tuple

log = logging.getLogger(__name__)

MAX_SLOTS = 16
_SCHEMA = """
CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE IF NOT EXISTS chunks (
    seq INTEGER PRIMARY KEY AUTOINCREMENT,
    rows INTEGER NOT NULL,
    data BLOB NOT NULL
);
"""
# Builtins a row may hold besides what pickle encodes without a global (tuple, dict, ...).
_ALLOWED = {("builtins", "bytearray"), ("builtins", "set"), ("builtins", "frozenset")}


class JournalError(Exception):
    """The journal file cannot be opened or written (a full disk, a permission)."""


class _RowsUnpickler(pickle.Unpickler):
    """Plain data only: a journal file can never make the gateway import or call anything."""

    def find_class(self, module: str, name: str) -> type:
        if (module, name) in _ALLOWED:
            found: type = super().find_class(module, name)
            return found
        raise pickle.UnpicklingError(f"journal entry refers to {module}.{name}")


def _dumps(rows: Sequence[Row]) -> bytes:
    # Rows as plain tuples (`Row.as_tuple`): the format every version of the journal has.
    return pickle.dumps([row.as_tuple() for row in rows], protocol=5)


def _loads(data: bytes) -> list[Row]:
    rows: object = _RowsUnpickler(io.BytesIO(data)).load()
    if not isinstance(rows, list):
        raise pickle.UnpicklingError("journal entry is not a list of rows")
    return [from_tuple(item) for item in rows]


def database_tag(database_url: str) -> str:
    """A short tag of the database (URL without password, schema option included)."""
    url = make_url(database_url)
    plain = url.render_as_string(hide_password=True)
    return hashlib.blake2b(plain.encode(), digest_size=4).hexdigest()


def default_journal_dir(database_url: str) -> Path:
    """Next to the database file on SQLite; the working directory (the state directory of a
    service or container) on PostgreSQL."""
    url = make_url(database_url)
    if url.get_backend_name() == "sqlite" and url.database and url.database != ":memory:":
        return Path(url.database).resolve().parent
    return Path.cwd()


class RowJournal:
    """A persistent FIFO of row chunks; thread-safe. Open with `RowJournal.open(...)`."""

    def __init__(self, path: Path, lock_fd: int, database: str) -> None:
        self.path = path
        self._lock_fd = lock_fd
        self._lock = threading.Lock()
        try:
            self._db = open_local_sqlite(path)
            self._db.executescript(_SCHEMA)
            row = self._db.execute("SELECT value FROM meta WHERE key = 'database'").fetchone()
            if row is None:
                self._db.execute(
                    "INSERT INTO meta (key, value) VALUES ('database', ?)", (database,)
                )
            elif row[0] != database:
                raise JournalError(f"journal {path} belongs to database {row[0]}, not {database}")
            (rows,) = self._db.execute("SELECT coalesce(sum(rows), 0) FROM chunks").fetchone()
            last = self._db.execute("SELECT coalesce(max(seq), 0) FROM chunks").fetchone()
        except sqlite3.Error as exc:
            os.close(lock_fd)
            raise JournalError(f"cannot open the journal {path}: {exc}") from exc
        except BaseException:
            os.close(lock_fd)
            raise
        self._rows = int(rows)
        # Entries up to this number were written by an earlier process (replayed at start).
        self.inherited_seq = int(last[0])
        self.inherited_rows = self._rows
        self.unreadable_rows = 0

    @classmethod
    def open(cls, directory: str | Path, database_url: str) -> RowJournal:
        """The first free slot for this database in `directory`, with the entries of the
        slots nobody holds moved into it."""
        folder = Path(directory)
        try:
            folder.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise JournalError(f"cannot create the journal folder {folder}: {exc}") from exc
        tag = database_tag(database_url)
        database = make_url(database_url).render_as_string(hide_password=True)
        paths = [
            folder / (f"eqgw-journal-{tag}.db" if i == 1 else f"eqgw-journal-{tag}-{i}.db")
            for i in range(1, MAX_SLOTS + 1)
        ]
        mine: RowJournal | None = None
        orphans: list[RowJournal] = []
        for path in paths:
            fd = _try_lock(path)
            if fd is None:
                continue  # another running gateway uses it
            if mine is None:
                mine = cls(path, fd, database)
            elif _has_data(path, fd):
                try:
                    orphans.append(cls(path, fd, database))
                except JournalError as exc:
                    log.warning("%s", exc)
            else:
                os.unlink(path)  # created by this probe (still locked: nobody else uses it)
                os.close(fd)
        if mine is None:
            raise JournalError(f"all {MAX_SLOTS} journal slots in {folder} are in use")
        for other in orphans:
            mine._adopt(other)
        return mine

    def _adopt(self, other: RowJournal) -> None:
        """Move another (dead) process's entries to the end of this journal."""
        moved = 0
        for _seq, rows in other.chunks():
            self.append(rows)
            moved += len(rows)
        other.close(remove=True)
        if moved:
            self.inherited_seq = self.last_seq()
            self.inherited_rows = self._rows
            log.warning("journal: took over %d rows left in %s", moved, other.path)

    # -- the FIFO --------------------------------------------------------------------------

    @property
    def rows(self) -> int:
        return self._rows

    def last_seq(self) -> int:
        with self._lock:
            row = self._db.execute(
                "SELECT seq FROM sqlite_sequence WHERE name = 'chunks'"
            ).fetchone()
            return int(row[0]) if row else 0

    def append(self, rows: Sequence[Row], chunk_rows: int = 20_000) -> None:
        """Append rows (one transaction, chunks of at most `chunk_rows`)."""
        if not rows:
            return
        items = list(rows)
        chunks = [items[i : i + chunk_rows] for i in range(0, len(items), chunk_rows)]
        with self._lock:
            try:
                with ImmediateTransaction(self._db):
                    self._db.executemany(
                        "INSERT INTO chunks (rows, data) VALUES (?, ?)",
                        [(len(c), _dumps(c)) for c in chunks],
                    )
            except sqlite3.Error as exc:
                raise JournalError(f"cannot write the journal {self.path}: {exc}") from exc
            self._rows += len(items)

    def first(self) -> tuple[int, list[Row]] | None:
        """The oldest entry as (seq, rows), or None. An entry that cannot be read (a damaged
        file) is logged, counted in `unreadable_rows` and forgotten."""
        while True:
            with self._lock:
                row = self._db.execute(
                    "SELECT seq, rows, data FROM chunks ORDER BY seq LIMIT 1"
                ).fetchone()
            if row is None:
                return None
            try:
                return int(row[0]), _loads(bytes(row[2]))
            except Exception as exc:
                log.error(
                    "journal %s: entry %d (%d rows) unreadable, dropped: %s",
                    self.path,
                    row[0],
                    row[1],
                    exc,
                )
                self.unreadable_rows += int(row[1])
                self.ack(int(row[0]))

    def first_seq(self) -> int | None:
        """The number of the oldest entry, or None when empty."""
        with self._lock:
            row = self._db.execute("SELECT min(seq) FROM chunks").fetchone()
        return None if row is None or row[0] is None else int(row[0])

    def chunks(self) -> list[tuple[int, list[Row]]]:
        with self._lock:
            cur = self._db.execute("SELECT seq, data FROM chunks ORDER BY seq")
            return [(int(s), _loads(bytes(d))) for s, d in cur]

    def ack(self, seq: int) -> None:
        """Forget the entry `seq` (the database has its rows)."""
        with self._lock:
            row = self._db.execute("SELECT rows FROM chunks WHERE seq = ?", (seq,)).fetchone()
            if row is None:
                return
            self._db.execute("DELETE FROM chunks WHERE seq = ?", (seq,))
            self._rows -= int(row[0])

    # -- the reserve: space kept free for a stop on a full disk ------------------------------

    @property
    def reserve_path(self) -> Path:
        """The preallocated file beside the journal whose blocks a stop on a full disk frees."""
        return self.path.with_name(self.path.name + ".reserve")

    def reserved_bytes(self) -> int:
        """Bytes the reserve holds on disk now (0 when there is none)."""
        try:
            return os.stat(self.reserve_path).st_blocks * 512
        except OSError:
            return 0

    def reserve(self, nbytes: int) -> int:
        """Keep `nbytes` of the journal's disk in reserve (a file of allocated blocks, made or
        resized now); returns the bytes reserved. A disk without that much room keeps what it
        can, and the log says so: a stop on a full disk may then lose rows."""
        path = self.reserve_path
        if nbytes <= 0:
            self.release_reserve()
            return 0
        try:
            fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o600)
        except OSError as exc:
            log.error(
                "journal: cannot reserve %d bytes in %s (%s): a stop on a full disk may lose rows",
                nbytes,
                path,
                exc,
            )
            return 0
        try:
            if os.fstat(fd).st_size > nbytes:
                os.ftruncate(fd, nbytes)
            try:
                os.posix_fallocate(fd, 0, nbytes)
            except OSError as exc:
                got = os.fstat(fd).st_blocks * 512
                log.error(
                    "journal: only %d of %d bytes reserved in %s (%s): a stop on a full disk "
                    "may lose rows",
                    got,
                    nbytes,
                    path,
                    exc,
                )
                return got
            return nbytes
        finally:
            os.close(fd)

    def release_reserve(self) -> int:
        """Free the reserve (its blocks become the journal's room); returns the bytes freed."""
        freed = self.reserved_bytes()
        with contextlib.suppress(FileNotFoundError):
            os.unlink(self.reserve_path)
        return freed

    def append_reserved(self, rows: Sequence[Row], chunk_rows: int = 20_000) -> int:
        """`append`, and when the disk is full, free the reserve and append again (at a stop:
        what the writer holds must go somewhere). Returns the bytes freed (0: not needed);
        raises JournalError when the rows do not fit even so."""
        try:
            self.append(rows, chunk_rows)
            return 0
        except JournalError as exc:
            freed = self.release_reserve()
            if not freed:
                raise
            log.warning("journal: %s; %d bytes of reserve freed for %d rows", exc, freed, len(rows))
        self.append(rows, chunk_rows)
        return freed

    def adopt_from(self, directory: str | Path, database_url: str) -> int:
        """Take over the entries of this database's journals in another folder (the second
        location, written at a stop when this one was full) that no running process holds;
        returns the rows moved. They are replayed with this journal's own."""
        folder = Path(directory)
        if not folder.is_dir() or folder.resolve() == self.path.parent.resolve():
            return 0
        tag = database_tag(database_url)
        database = make_url(database_url).render_as_string(hide_password=True)
        before = self._rows
        for i in range(1, MAX_SLOTS + 1):
            path = folder / (f"eqgw-journal-{tag}.db" if i == 1 else f"eqgw-journal-{tag}-{i}.db")
            if not path.exists():
                continue
            fd = _try_lock(path)
            if fd is None:
                continue  # another running gateway uses it
            if not _has_data(path, fd):
                os.unlink(path)
                os.close(fd)
                continue
            try:
                self._adopt(RowJournal(path, fd, database))
            except JournalError as exc:
                log.warning("%s", exc)
        return self._rows - before

    def size_bytes(self) -> int:
        """Bytes on disk (the file and its WAL)."""
        total = 0
        for p in (self.path, self.path.with_name(self.path.name + "-wal")):
            with contextlib.suppress(OSError):
                total += p.stat().st_size
        return total

    def close(self, *, remove: bool | None = None) -> None:
        """Close; an empty journal's files are removed (`remove` forces either way)."""
        with self._lock:
            empty = self._rows == 0
            with contextlib.suppress(sqlite3.Error):
                self._db.close()
            # Removed while still locked, so nobody else can be using these files.
            with contextlib.suppress(OSError):  # made again at the next start
                os.unlink(self.reserve_path)
            if remove if remove is not None else empty:
                for suffix in ("-wal", "-shm", ""):
                    with contextlib.suppress(OSError):
                        os.unlink(f"{self.path}{suffix}")
            if self._lock_fd >= 0:
                os.close(self._lock_fd)
                self._lock_fd = -1


def _try_lock(path: Path) -> int | None:
    """An exclusive lock on the journal file itself (flock, which SQLite's own POSIX locks
    do not touch), or None when another process holds it. The kernel frees it when the
    process ends, however it ends."""
    while True:
        # 0600: the journal holds fleet data, the owner's only (as the database's files).
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o600)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(fd)
            return None
        try:
            same = os.stat(path).st_ino == os.fstat(fd).st_ino
        except FileNotFoundError:
            same = False
        if same:
            return fd
        os.close(fd)  # removed by its owner between our open and our lock: open it again


def _has_data(path: Path, fd: int) -> bool:
    """Whether a journal file holds anything (in WAL mode it may all be in the -wal file)."""
    if os.fstat(fd).st_size > 0:
        return True
    try:
        return os.stat(f"{path}-wal").st_size > 0
    except OSError:
        return False
