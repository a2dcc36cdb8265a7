"""The forwarder's local buffer: frames in a SQLite file (WAL) until the central service has them.

Every frame gets a sequence number (SQLite AUTOINCREMENT: monotonic, never reused, even after
the buffer has been emptied), so uploads can be acknowledged by number. The buffer survives
power loss: WAL keeps the file consistent (a cut may lose the last commits, frames that were
never acknowledged to anyone). It is bounded by rows and by bytes; when full, the oldest frames
are dropped and counted. A new buffer file gets a new stream id, so the central service never
mistakes its sequence numbers for an older buffer's.
"""

from __future__ import annotations

import sqlite3
import threading
import time
import uuid
from collections.abc import Iterable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from eqgw.files import ImmediateTransaction, open_local_sqlite

# Bytes a row is counted as besides its data: seq, ts, id, flags and SQLite's own overhead.
ROW_OVERHEAD_BYTES = 32

Frame = tuple[float, int, bytes, int]  # ts, can_id, data, flags

_SCHEMA = """
CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE IF NOT EXISTS frames (
    seq INTEGER PRIMARY KEY AUTOINCREMENT,
    ts REAL NOT NULL,
    can_id INTEGER NOT NULL,
    data BLOB NOT NULL,
    flags INTEGER NOT NULL
);
"""


@dataclass(slots=True)
class BufferStatus:
    """What the buffer holds and has lost."""

    stream: str
    rows: int
    bytes: int
    max_rows: int
    max_bytes: int
    last_seq: int  # the newest sequence number given out (0: none yet)
    acked_seq: int  # the newest acknowledged by the central service
    dropped: int  # frames dropped because the buffer was full, since it was created

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)


class FrameBuffer:
    """A bounded, persistent FIFO of frames with sequence numbers; thread-safe."""

    def __init__(
        self, path: str | Path, *, max_rows: int = 5_000_000, max_bytes: int = 1 << 30
    ) -> None:
        if max_rows < 1 or max_bytes < ROW_OVERHEAD_BYTES:
            raise ValueError("the buffer must hold at least one frame")
        self.path = Path(path)
        self.max_rows = max_rows
        self.max_bytes = max_bytes
        self._lock = threading.Lock()
        self._db = open_local_sqlite(self.path)  # frames and the stream id: 0600
        self._db.executescript(_SCHEMA)
        with self._tx():
            self.stream = self._meta("stream") or self._set_meta("stream", uuid.uuid4().hex)
            self._dropped = int(self._meta("dropped") or 0)
            self._acked = int(self._meta("acked_seq") or 0)
        self._dropped_unsaved = False
        # Frames forgotten on an acknowledgement since this buffer was opened, and when the
        # last acknowledgement came: kept with the row count, so that whoever reads the buffer
        # empty also reads them counted.
        self._forgotten = 0
        self._acked_at: float | None = None
        rows, data = self._db.execute(
            "SELECT count(*), coalesce(sum(length(data)), 0) FROM frames"
        ).fetchone()
        self._rows = int(rows)
        self._bytes = int(data) + ROW_OVERHEAD_BYTES * self._rows

    # -- helpers ---------------------------------------------------------------------------

    def _tx(self) -> ImmediateTransaction:
        return ImmediateTransaction(self._db)

    def _meta(self, key: str) -> str | None:
        row = self._db.execute("SELECT value FROM meta WHERE key = ?", (key,)).fetchone()
        return None if row is None else str(row[0])

    def _set_meta(self, key: str, value: str) -> str:
        self._db.execute(
            "INSERT INTO meta (key, value) VALUES (?, ?) "
            "ON CONFLICT (key) DO UPDATE SET value = excluded.value",
            (key, value),
        )
        return value

    def _last_seq(self) -> int:
        row = self._db.execute("SELECT seq FROM sqlite_sequence WHERE name = 'frames'").fetchone()
        return int(row[0]) if row else 0

    # -- the FIFO --------------------------------------------------------------------------

    def add(self, frames: Iterable[Frame]) -> int:
        """Append frames (one transaction); drops the oldest beyond the bounds. Returns the
        number of frames dropped by this call."""
        rows = list(frames)
        if not rows:
            return 0
        added_bytes = sum(len(r[2]) for r in rows) + ROW_OVERHEAD_BYTES * len(rows)
        with self._lock:
            before = (self._rows, self._bytes, self._dropped)
            try:
                with self._tx():
                    self._db.executemany(
                        "INSERT INTO frames (ts, can_id, data, flags) VALUES (?, ?, ?, ?)", rows
                    )
                    self._rows += len(rows)
                    self._bytes += added_bytes
                    dropped = self._enforce_bounds()
                    if self._dropped_unsaved and not dropped:
                        self._set_meta("dropped", str(self._dropped))
            except sqlite3.Error:
                # Not kept (the disk is full, the file went bad): counted as dropped, and the
                # count saved with the next frames that are kept.
                self._rows, self._bytes, self._dropped = before
                self._dropped += len(rows)
                self._dropped_unsaved = True
                raise
            self._dropped_unsaved = False
            return dropped

    def _enforce_bounds(self) -> int:
        if self._rows <= self.max_rows and self._bytes <= self.max_bytes:
            return 0
        excess_rows = max(0, self._rows - self.max_rows)
        # Walk the oldest rows until enough bytes are freed too (in chunks, oldest first).
        drop_to = None
        freed_rows = freed_bytes = 0
        need_bytes = max(0, self._bytes - self.max_bytes)
        cursor = self._db.execute("SELECT seq, length(data) FROM frames ORDER BY seq")
        while freed_rows < excess_rows or freed_bytes < need_bytes:
            chunk = cursor.fetchmany(4096)
            if not chunk:
                break
            for seq, size in chunk:
                drop_to = seq
                freed_rows += 1
                freed_bytes += size + ROW_OVERHEAD_BYTES
                if freed_rows >= excess_rows and freed_bytes >= need_bytes:
                    break
        cursor.close()
        if drop_to is None:
            return 0
        self._db.execute("DELETE FROM frames WHERE seq <= ?", (drop_to,))
        self._rows -= freed_rows
        self._bytes -= freed_bytes
        self._dropped += freed_rows
        self._set_meta("dropped", str(self._dropped))
        return freed_rows

    def peek(self, limit: int) -> list[tuple[int, float, int, bytes, int]]:
        """Up to `limit` of the oldest frames as (seq, ts, can_id, data, flags)."""
        with self._lock:
            cur = self._db.execute(
                "SELECT seq, ts, can_id, data, flags FROM frames ORDER BY seq LIMIT ?", (limit,)
            )
            return [(int(s), float(t), int(c), bytes(d), int(f)) for s, t, c, d, f in cur]

    def ack(self, seq: int) -> int:
        """Forget frames up to `seq` (the central service has stored them); returns how many."""
        with self._lock, self._tx():
            rows, data = self._db.execute(
                "SELECT count(*), coalesce(sum(length(data)), 0) FROM frames WHERE seq <= ?",
                (seq,),
            ).fetchone()
            self._db.execute("DELETE FROM frames WHERE seq <= ?", (seq,))
            self._forgotten += int(rows)
            self._acked_at = time.time()
            self._rows -= int(rows)
            self._bytes -= int(data) + ROW_OVERHEAD_BYTES * int(rows)
            if seq > self._acked:
                self._acked = seq
                self._set_meta("acked_seq", str(seq))
            return int(rows)

    @property
    def dropped(self) -> int:
        return self._dropped

    @property
    def rows(self) -> int:
        return self._rows

    def acknowledged(self) -> tuple[int, float | None]:
        """Frames forgotten on an acknowledgement since this buffer was opened, and when the
        last acknowledgement was taken (time.time(), None before the first): read together,
        as `ack` changes them."""
        with self._lock:
            return self._forgotten, self._acked_at

    def status(self) -> BufferStatus:
        """A snapshot of the counters."""
        with self._lock:
            return BufferStatus(
                stream=self.stream,
                rows=self._rows,
                bytes=self._bytes,
                max_rows=self.max_rows,
                max_bytes=self.max_bytes,
                last_seq=self._last_seq(),
                acked_seq=self._acked,
                dropped=self._dropped,
            )

    def close(self) -> None:
        with self._lock:
            self._db.close()

    def __enter__(self) -> FrameBuffer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
