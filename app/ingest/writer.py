"""The batched database writer: a thread that commits rows in batches and rides out outages."""

from __future__ import annotations

import asyncio
import logging
import threading
import time
from collections import deque
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from typing import Any

from sqlalchemy import Engine
from sqlalchemy.exc import SQLAlchemyError

from app.config import WriterSettings
from app.describe import describe
from app.store.writes import Batch, UnitKey, load_unit_ids, write_batch

log = logging.getLogger(__name__)

# Row kinds the writer accepts: (kind, key, payload).
#   vehicle: key vehicle id, payload {id, name, depot}
#   unit: key (bus, sa), payload vehicle id
#   unit_info: key (bus, sa), payload {series, model, software_id}
#   seen: key (bus, sa), payload (first ts, last ts)
#   measurements, battery_states, status_changes, dm1_snapshots, messages, raw_frames:
#       key (bus, sa), payload the row without unit_id
#   episode: key ((bus, sa), fault, started_at), payload the row without unit_id
#   live: key ((bus, sa), name), payload {ts, fields}
Item = tuple[str, Any, Any]
_LISTS = frozenset(
    {"measurements", "battery_states", "status_changes", "dm1_snapshots", "messages", "raw_frames"}
)


@dataclass(slots=True)
class WriterStatus:
    """What the writer holds and has done; reported by `eqgw replay` and the API."""

    state: str  # idle, writing, retrying, stopped
    pending_rows: int
    max_pending_rows: int
    accepted_rows: int
    committed_rows: int
    batches: int
    failures: int
    consecutive_failures: int
    last_error: str | None
    backpressure_waits: int
    refused_rows: int
    inserted: dict[str, int]
    # Seconds the oldest row accepted and not yet committed has waited (0 when none waits).
    lag_s: float = 0.0

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)


def build_batch(items: Sequence[Item]) -> Batch:
    """Group queued items by destination, coalescing repeated upserts of the same key."""
    batch = Batch(rows=len(items))
    # The row lists take most items: one dict lookup finds the list's append.
    appends = {kind: getattr(batch, kind).append for kind in _LISTS}
    live, episodes, seen = batch.live, batch.episodes, batch.seen
    for item in items:
        kind, key, payload = item
        append = appends.get(kind)
        if append is not None:
            append((key, payload))
        elif kind == "live":
            prev = live.get(key)
            if prev is None or prev["ts"] <= payload["ts"]:
                live[key] = payload
        elif kind == "episode":
            episodes[key] = payload  # later state of the same episode wins
        elif kind == "seen":
            cur = seen.get(key)
            if cur is None:
                seen[key] = [payload[0], payload[1]]
            else:
                cur[0] = min(cur[0], payload[0])
                cur[1] = max(cur[1], payload[1])
        elif kind == "unit":
            batch.units[key] = payload
        elif kind == "unit_info":
            batch.unit_info.setdefault(key, {}).update(payload)
        elif kind == "vehicle":
            batch.vehicles[key] = payload
        else:
            raise ValueError(f"unknown row kind {kind!r}")
    return batch


class BatchedWriter:
    """Accepts rows from the ingest and commits them from one thread, one batch per transaction.

    Nothing accepted is dropped: a failed batch stays at the head and is retried with
    exponential backoff while new rows queue behind it, up to `max_pending_rows`.
    """

    def __init__(self, engine: Engine, settings: WriterSettings | None = None) -> None:
        self.engine = engine
        self.settings = settings or WriterSettings()
        self._cond = threading.Condition()
        self._queue: deque[Item] = deque()
        self._inflight = 0
        self._stopping = False
        self._thread: threading.Thread | None = None
        self._units: dict[UnitKey, int] = {}
        self._state = "idle"
        self._accepted = 0
        self._committed = 0
        self._batches = 0
        self._failures = 0
        self._consecutive = 0
        self._last_error: str | None = None
        self._waits = 0
        self._refused = 0
        self._inserted: dict[str, int] = {}
        self._flush_waiters = 0
        # (rows accepted up to and including a call of _accept, when): the oldest mark past
        # what is committed dates the oldest waiting row (the writer's lag).
        self._marks: deque[tuple[int, float]] = deque()
        # SQLite writers take the write lock at BEGIN (see app.store.engine).
        self._write_engine = (
            engine.execution_options(sqlite_begin="IMMEDIATE")
            if engine.dialect.name == "sqlite"
            else engine
        )

    # -- lifecycle -----------------------------------------------------------------------

    def start(self) -> None:
        """Start the writer thread (the units table is read on its first batch)."""
        if self._thread is not None:
            return
        self._thread = threading.Thread(target=self._run, name="eqgw-writer", daemon=True)
        self._thread.start()

    def stop(self, timeout: float | None = 30.0) -> int:
        """Commit what is pending, then stop; returns the rows left unwritten (0 normally)."""
        with self._cond:
            self._stopping = True
            self._cond.notify_all()
        if self._thread is not None:
            self._thread.join(timeout)
            if self._thread.is_alive():
                log.error(
                    "writer stopped with %d rows unwritten: %s", self.pending, self._last_error
                )
        self._state = "stopped"
        return self.pending

    @property
    def pending(self) -> int:
        return len(self._queue) + self._inflight

    # -- accepting rows --------------------------------------------------------------------

    def offer(self, items: Sequence[Item]) -> bool:
        """Accept all of `items` if they fit under the memory bound, else none (counted)."""
        with self._cond:
            if self.pending + len(items) > self.settings.max_pending_rows and self.pending:
                self._refused += len(items)
                return False
            self._accept(items)
            return True

    def put(self, items: Sequence[Item], timeout: float | None = None) -> bool:
        """Accept `items`, waiting for room (backpressure); False if `timeout` passed first."""
        deadline = None if timeout is None else time.monotonic() + timeout
        with self._cond:
            waited = False
            while self.pending + len(items) > self.settings.max_pending_rows and self.pending:
                if not waited:
                    self._waits += 1
                    waited = True
                remaining = None if deadline is None else deadline - time.monotonic()
                if remaining is not None and remaining <= 0:
                    return False
                self._cond.wait(remaining if remaining is not None else 0.5)
            self._accept(items)
            return True

    async def put_async(self, items: Sequence[Item]) -> None:
        """Accept `items`, yielding to the event loop while the writer is full."""
        if self.offer_quiet(items):
            return
        self._waits += 1
        while not self.offer_quiet(items):
            await asyncio.sleep(0.05)

    def offer_quiet(self, items: Sequence[Item]) -> bool:
        """Like `offer`, without counting a refusal (for callers that will retry)."""
        with self._cond:
            if self.pending + len(items) > self.settings.max_pending_rows and self.pending:
                return False
            self._accept(items)
            return True

    def _accept(self, items: Sequence[Item]) -> None:
        self._queue.extend(items)
        self._accepted += len(items)
        self._marks.append((self._accepted, time.monotonic()))
        if len(self._queue) >= self.settings.batch_rows:
            self._cond.notify_all()

    def flush(self, timeout: float | None = None) -> bool:
        """Wait until everything accepted so far is committed; False on timeout."""
        deadline = None if timeout is None else time.monotonic() + timeout
        with self._cond:
            target = self._accepted
            self._flush_waiters += 1
            self._cond.notify_all()
            try:
                while self._committed < target:
                    remaining = None if deadline is None else deadline - time.monotonic()
                    if remaining is not None and remaining <= 0:
                        return False
                    self._cond.wait(min(remaining, 0.5) if remaining is not None else 0.5)
            finally:
                self._flush_waiters -= 1
        return True

    def status(self) -> WriterStatus:
        """A snapshot of the counters."""
        with self._cond:
            return WriterStatus(
                state=self._state,
                pending_rows=self.pending,
                max_pending_rows=self.settings.max_pending_rows,
                lag_s=self._lag(),
                accepted_rows=self._accepted,
                committed_rows=self._committed,
                batches=self._batches,
                failures=self._failures,
                consecutive_failures=self._consecutive,
                last_error=self._last_error,
                backpressure_waits=self._waits,
                refused_rows=self._refused,
                inserted=dict(self._inserted),
            )

    def _lag(self) -> float:
        """Age of the oldest row not yet committed (call with the lock held)."""
        marks = self._marks
        while marks and marks[0][0] <= self._committed:
            marks.popleft()
        return time.monotonic() - marks[0][1] if marks else 0.0

    # -- the thread ------------------------------------------------------------------------

    def _take(self) -> list[Item] | None:
        """Wait for a batch worth of rows, the flush interval, a flush() caller, or stop."""
        flush_s = self.settings.flush_ms / 1000.0
        with self._cond:
            while not self._queue and not self._stopping:
                self._cond.wait(1.0)
            deadline = time.monotonic() + flush_s
            while (
                not self._stopping
                and not self._flush_waiters
                and len(self._queue) < self.settings.batch_rows
            ):
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    break
                self._cond.wait(remaining)
            if not self._queue:
                return None
            n = min(len(self._queue), self.settings.batch_rows)
            items = [self._queue.popleft() for _ in range(n)]
            self._inflight = n
            return items

    def _run(self) -> None:
        delay = self.settings.retry_initial_s
        while True:
            items = self._take()
            if items is None:
                break  # stopping, nothing left
            batch = build_batch(items)
            while True:
                try:
                    self._state = "writing"
                    self._write(batch)
                except (SQLAlchemyError, OSError) as exc:
                    with self._cond:
                        self._failures += 1
                        self._consecutive += 1
                        self._last_error = describe(exc)
                        self._state = "retrying"
                        stopping = self._stopping
                    if self._consecutive == 1 or self._consecutive % 10 == 0:
                        log.warning(
                            "database write failed (%d in a row, %d rows held), retrying in "
                            "%.1fs: %s",
                            self._consecutive,
                            self.pending,
                            delay,
                            self._last_error,
                        )
                    # While stopping, keep trying until stop()'s join times out.
                    time.sleep(delay if not stopping else min(delay, 1.0))
                    delay = min(delay * 2, self.settings.retry_max_s)
                    continue
                with self._cond:
                    self._inflight = 0
                    self._committed += batch.rows
                    self._batches += 1
                    self._lag()  # drop the marks of what is committed
                    if self._consecutive:
                        log.warning("database writes resumed after %d failures", self._consecutive)
                    self._consecutive = 0
                    self._state = "idle"
                    self._cond.notify_all()
                delay = self.settings.retry_initial_s
                break

    def _write(self, batch: Batch) -> None:
        try:
            self._write_once(batch)
        except KeyError:
            # A unit registered by another process (another gateway on the same database)
            # after this writer loaded the ids: load them again, once.
            self._units = {}
            self._write_once(batch)

    def _write_once(self, batch: Batch) -> None:
        with self._write_engine.begin() as conn:
            if not self._units:
                self._units = load_unit_ids(conn)
            result = write_batch(conn, batch, self._units)
        # Only after the commit: ids of a rolled-back insert may not exist on retry.
        self._units.update(result.unit_ids)
        for name, n in result.inserted.items():
            self._inserted[name] = self._inserted.get(name, 0) + n
