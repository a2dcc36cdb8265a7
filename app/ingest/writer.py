"""The batched database writer: a thread that commits rows in batches and rides out outages."""

from __future__ import annotations

import asyncio
import logging
import threading
import time
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass
from typing import assert_never

from sqlalchemy import Engine
from sqlalchemy.exc import SQLAlchemyError

from eqgw.config import WriterSettings
from eqgw.describe import describe
from eqgw.ingest.journal import JournalError, RowJournal
from eqgw.ingest.rows import (
    BatteryStateRow,
    Dm1SnapshotRow,
    EpisodeRow,
    LiveRow,
    MeasurementRow,
    MessageRow,
    RawFrameRow,
    Row,
    SeenRow,
    StatusChangeRow,
    UnitInfoRow,
    UnitOwnerRow,
    UnitRow,
    VehicleRow,
)
from eqgw.jsontypes import JSONObject
from eqgw.store import archive, packed
from eqgw.store.engine import db_deadline
from eqgw.store.writes import Batch, UnitKey, load_unit_ids, write_batch

log = logging.getLogger(__name__)


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
    # Rows in the local journal (spilled during an outage or at stop), and where it is.
    journal_rows: int = 0
    journal_path: str | None = None
    spilled_rows: int = 0  # moved to the journal by this process
    replayed_rows: int = 0  # left in the journal by an earlier process, now committed
    journal_errors: int = 0  # journal writes that failed (the rows stayed in memory)
    rejected_rows: int = 0  # rows that could not be built into a batch (logged, dropped)
    crashes: int = 0  # unexpected errors of the writer thread (each logged; it went on)
    compacted_frames: int = 0  # raw frames this writer packed into the archive's blocks

    def as_dict(self) -> JSONObject:
        return asdict(self)


def build_batch(items: Sequence[Row]) -> Batch:
    """Group queued rows by destination, coalescing repeated upserts of the same key."""
    batch = Batch(rows=len(items))
    live, episodes, seen = batch.live, batch.episodes, batch.seen
    # The most frequent rows first: each test is one isinstance (a `match` of class
    # patterns costs about twice as much per row).
    for item in items:
        if isinstance(item, RawFrameRow):
            batch.raw_frames.append((item.key, item.values))
        elif isinstance(item, BatteryStateRow):
            batch.battery_states.append((item.key, item.values))
        elif isinstance(item, MeasurementRow):
            batch.measurements.append((item.key, item.values))
        elif isinstance(item, LiveRow):
            prev = live.get(item.key)
            if prev is None or prev["ts"] <= item.values["ts"]:
                live[item.key] = item.values
        elif isinstance(item, EpisodeRow):
            episodes[item.key] = item.values  # later state of the same episode wins
        elif isinstance(item, MessageRow):
            batch.messages.append((item.key, item.values))
        elif isinstance(item, StatusChangeRow):
            batch.status_changes.append((item.key, item.values))
        elif isinstance(item, Dm1SnapshotRow):
            batch.dm1_snapshots.append((item.key, item.values))
        elif isinstance(item, SeenRow):
            cur = seen.get(item.key)
            if cur is None:
                seen[item.key] = [item.first, item.last]
            else:
                cur[0] = min(cur[0], item.first)
                cur[1] = max(cur[1], item.last)
        elif isinstance(item, UnitRow):
            batch.units[item.key] = item.vehicle_id
        elif isinstance(item, UnitInfoRow):
            batch.unit_info.setdefault(item.key, {}).update(item.info)
        elif isinstance(item, UnitOwnerRow):
            # Identification gathered before the change of owner was the previous node's.
            known = batch.unit_info.get(item.key)
            if known is not None and known.get("ts", item.since) < item.since:
                del batch.unit_info[item.key]
            batch.unit_owners.setdefault(item.key, []).append((item.since, item.name))
        elif isinstance(item, VehicleRow):
            batch.vehicles[item.vehicle_id] = item.info
        else:
            assert_never(item)
    return batch


class BatchedWriter:
    """Accepts rows from the ingest and commits them from one thread, one batch per transaction.

    Nothing accepted is dropped: a failed batch stays at the head and is retried with
    exponential backoff while new rows queue behind it, up to `max_pending_rows` in memory.
    With a journal (app/ingest/journal.py), once the database has failed for `spill_after_s`
    the rows held are moved to it and, while the outage lasts, new rows every flush interval;
    at stop, rows that cannot be committed go there too. The journal is written to the
    database first (it is older than anything in memory), the next start included.
    An unexpected error in the thread is logged, counted as a failure (readiness turns false)
    and the thread's loop starts again with the rows it held.

    Between batches, every `archive.COMPACT_EVERY_S` while the database answers, the thread
    packs the raw archive's minutes that are due (`eqgw.store.archive.compact`): it is the one
    thread that writes the time series, so packing never races its own batches.
    """

    def __init__(
        self,
        engine: Engine,
        settings: WriterSettings | None = None,
        *,
        journal: RowJournal | None = None,
        compact_raw: bool = True,
    ) -> None:
        self.engine = engine
        self.settings = settings or WriterSettings()
        self.journal = journal
        self.compact_raw = compact_raw
        # The first packing soon after the start (minutes left by the previous run).
        self._next_compact = time.monotonic() + 1.0
        self._compacted = 0
        self._compact_failures = 0
        self._packed_rows = 0  # measurements and battery states packed (eqgw.store.packed)
        self._pack_failures = 0
        # The second journal location for a stop the journal cannot take (opened then only).
        self.journal_fallback: Callable[[], RowJournal] | None = None
        self._cond = threading.Condition()
        self._queue: deque[Row] = deque()
        self._held: list[Row] | None = None  # the batch taken from memory, not yet committed
        self._inflight = 0
        self._spilling = 0  # rows on their way to the journal (still counted as held)
        self._stopping = False
        self._thread: threading.Thread | None = None
        self._units: dict[UnitKey, int] = {}
        self._state = "idle"
        self._accepted = 0
        self._committed = 0
        self._batches = 0
        self._failures = 0
        self._consecutive = 0
        self._outage_since: float | None = None
        self._last_error: str | None = None
        self._waits = 0
        self._refused = 0
        self._rejected = 0
        self._crashes = 0
        self._spilled = 0
        self._replayed = 0
        self._journal_errors = 0
        self._inserted: dict[str, int] = {}
        self._flush_waiters = 0
        # (rows accepted up to and including a call of _accept, when): the oldest mark past
        # what is settled dates the oldest waiting row (the writer's lag).
        self._marks: deque[tuple[int, float]] = deque()
        # SQLite writers take the write lock at BEGIN (see eqgw.store.engine).
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
        """Commit what is held, else (the database away, with a journal) move it to the
        journal, then stop; returns the rows left neither committed nor journaled."""
        with self._cond:
            self._stopping = True
            self._cond.notify_all()
        alive = False
        if self._thread is not None:
            self._thread.join(timeout)
            alive = self._thread.is_alive()
            if alive and self.journal is not None:
                # A write that hangs (a database host gone without a word): what it holds
                # goes to the journal from here; should the write still succeed, the journal's
                # copy is written again at the next start, which adds nothing (natural keys).
                self._spill()
        if not alive:
            self._spill_at_stop()
        left = self.pending
        if left:
            log.error("writer stopped with %d rows unwritten: %s", left, self._last_error)
        j = self.journal
        if j is not None:
            if j.rows:
                log.warning(
                    "writer stopped: %d rows kept in the journal %s, written at the next start",
                    j.rows,
                    j.path,
                )
            if not alive:
                j.close()
        self._state = "stopped"
        return left

    @property
    def pending(self) -> int:
        """Rows held in memory (the journal's are counted by `status().journal_rows`)."""
        return len(self._queue) + self._inflight + self._spilling

    def wait_replayed(self, timeout: float) -> bool:
        """Wait until the rows an earlier process left in the journal are committed."""
        j = self.journal
        if j is None:
            return True
        deadline = time.monotonic() + timeout
        while (first := j.first_seq()) is not None and first <= j.inherited_seq:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                return False
            with self._cond:
                self._cond.wait(min(remaining, 0.2))
        return True

    # -- accepting rows --------------------------------------------------------------------

    def offer(self, items: Sequence[Row]) -> bool:
        """Accept all of `items` if they fit under the memory bound, else none (counted)."""
        with self._cond:
            if self.pending + len(items) > self.settings.max_pending_rows and self.pending:
                self._refused += len(items)
                return False
            self._accept(items)
            return True

    def put(self, items: Sequence[Row], timeout: float | None = None) -> bool:
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

    async def put_async(self, items: Sequence[Row]) -> None:
        """Accept `items`, yielding to the event loop while the writer is full."""
        if self.offer_quiet(items):
            return
        self._waits += 1
        while not self.offer_quiet(items):
            await asyncio.sleep(0.05)

    def offer_quiet(self, items: Sequence[Row]) -> bool:
        """Like `offer`, without counting a refusal (for callers that will retry)."""
        with self._cond:
            if self.pending + len(items) > self.settings.max_pending_rows and self.pending:
                return False
            self._accept(items)
            return True

    def _accept(self, items: Sequence[Row]) -> None:
        self._queue.extend(items)
        self._accepted += len(items)
        self._marks.append((self._accepted, time.monotonic()))
        if len(self._queue) >= self.settings.batch_rows:
            self._cond.notify_all()

    @property
    def _settled(self) -> int:
        """Rows accepted by this process and finished with: committed, or rejected."""
        return self._committed + self._rejected

    def flush(self, timeout: float | None = None) -> bool:
        """Wait until everything accepted so far is committed; False on timeout."""
        deadline = None if timeout is None else time.monotonic() + timeout
        with self._cond:
            target = self._accepted
            self._flush_waiters += 1
            self._cond.notify_all()
            try:
                while self._settled < target:
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
            state = self._state
            if self._thread is not None and not self._thread.is_alive() and not self._stopping:
                state = "dead"
            j = self.journal
            return WriterStatus(
                state=state,
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
                journal_rows=j.rows if j is not None else 0,
                journal_path=str(j.path) if j is not None else None,
                spilled_rows=self._spilled,
                replayed_rows=self._replayed,
                journal_errors=self._journal_errors,
                rejected_rows=self._rejected,
                crashes=self._crashes,
                compacted_frames=self._compacted,
            )

    def _lag(self) -> float:
        """Age of the oldest row not yet committed (call with the lock held)."""
        marks = self._marks
        settled = self._settled
        while marks and marks[0][0] <= settled:
            marks.popleft()
        return time.monotonic() - marks[0][1] if marks else 0.0

    # -- the thread ------------------------------------------------------------------------

    def _take(self) -> list[Row] | None:
        """Wait for a batch worth of rows, the flush interval, a flush() caller, or stop."""
        flush_s = self.settings.flush_ms / 1000.0
        with self._cond:
            while not self._queue and not self._stopping:
                if self._compaction_due():
                    return []  # the loop packs the archive, then comes back
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
            self._held = items
            self._inflight = n
            return items

    def _next(self) -> tuple[int | None, list[Row]] | None:
        """The next batch: (journal entry number, rows) while the journal holds rows (they are
        older than anything in memory), else (None, rows taken from memory); None to end."""
        j = self.journal
        if self._held is not None:  # a batch kept over a restart of the loop
            return None, self._held
        if j is not None and j.rows:
            with self._cond:
                stopping = self._stopping
            if stopping:
                self._spill()  # behind the journal's rows, for the next start
                return None
            entry = j.first()
            if entry is not None:
                return entry
        items = self._take()
        return None if items is None else (None, items)

    def _run(self) -> None:
        while True:
            try:
                self._loop()
                return
            except Exception as exc:  # a bug or a journal that cannot be read: never silent
                with self._cond:
                    self._crashes += 1
                    self._failures += 1
                    self._consecutive += 1
                    if self._outage_since is None:
                        self._outage_since = time.monotonic()
                    self._last_error = f"writer error: {describe(exc)}"
                    self._state = "failed"
                    stopping = self._stopping
                    n = self._crashes
                if n == 1 or n % 10 == 0:  # the same error every second: not a flood
                    log.exception(
                        "database writer failed (%d times, %d rows held); restarting it",
                        n,
                        self.pending,
                    )
                if stopping and self.journal is not None:
                    self._spill()
                    return
                with self._cond:
                    self._cond.wait(1.0)

    def _loop(self) -> None:
        delay = self.settings.retry_initial_s
        while True:
            taken = self._next()
            if taken is None:
                return  # stopping, nothing left in memory
            seq, items = taken
            if not items:
                self._compact()
                continue
            batch = self._build(items)
            while True:
                began = time.monotonic()
                try:
                    with self._cond:
                        self._state = "writing"
                    self._write(batch)
                except (SQLAlchemyError, OSError) as exc:
                    with self._cond:
                        self._failures += 1
                        self._consecutive += 1
                        if self._outage_since is None:
                            # From the attempt's start: a write that hung until its deadline
                            # was the outage's first seconds.
                            self._outage_since = began
                        self._last_error = describe(exc)
                        self._state = "retrying"
                        stopping = self._stopping
                    if self._consecutive == 1 or self._consecutive % 10 == 0:
                        log.warning(
                            "database write failed (%d in a row, %d rows held, %d in the "
                            "journal), retrying in %.1fs: %s",
                            self._consecutive,
                            self.pending,
                            self.journal.rows if self.journal is not None else 0,
                            delay,
                            self._last_error,
                        )
                    if stopping and self.journal is not None:
                        self._spill()  # kept for the next start instead of retried
                        return
                    # While stopping without a journal, keep trying until stop()'s join
                    # times out.
                    moved = self._backoff(delay if not stopping else min(delay, 1.0))
                    delay = min(delay * 2, self.settings.retry_max_s)
                    if moved:
                        break  # the batch went to the journal: take it from there
                    continue
                self._done(seq, len(items), batch.rows)
                delay = self.settings.retry_initial_s
                if self._compaction_due():
                    self._compact()
                break

    def _compaction_due(self) -> bool:
        """Whether to pack the raw archive now: its period passed, the database answers."""
        return (
            self.compact_raw
            and not self._consecutive
            and not self._stopping
            and time.monotonic() >= self._next_compact
        )

    def _compact(self) -> None:
        """Pack the raw archive's minutes that are due, then the measurements and battery
        states of the hours that are due, each for at most about a second (rows queue
        meanwhile; a backlog is packed over the next periods). A failure is logged and left
        for the next period: the frames wait in raw_recent, the rows in their tables,
        nothing is lost."""
        self._next_compact = time.monotonic() + archive.COMPACT_EVERY_S
        try:
            with db_deadline(self.settings.write_timeout_s):
                n = archive.compact(self._write_engine, budget_s=1.0)
        except (SQLAlchemyError, OSError, archive.ArchiveError) as exc:
            self._compact_failures += 1
            if self._compact_failures == 1 or self._compact_failures % 10 == 0:
                log.warning(
                    "packing the raw archive failed (%d times), retried in %.0f s: %s",
                    self._compact_failures,
                    archive.COMPACT_EVERY_S,
                    describe(exc),
                )
        else:
            self._compact_failures = 0
            with self._cond:
                self._compacted += n
        self._pack_series()

    def _pack_series(self) -> None:
        """Pack the measurements and battery states of the hours that are due, for at most
        about a second; a failure is logged and left for the next period (the rows stay in
        their tables, read as before)."""
        try:
            with db_deadline(self.settings.write_timeout_s):
                n = packed.compact(self._write_engine, budget_s=1.0)
        except (SQLAlchemyError, OSError, packed.PackedError) as exc:
            self._pack_failures += 1
            if self._pack_failures == 1 or self._pack_failures % 10 == 0:
                log.warning(
                    "packing measurements and battery states failed (%d times), retried in "
                    "%.0f s: %s",
                    self._pack_failures,
                    archive.COMPACT_EVERY_S,
                    describe(exc),
                )
            return
        self._pack_failures = 0
        with self._cond:
            self._packed_rows += n

    def _build(self, items: list[Row]) -> Batch:
        """The batch of `items`; rows it cannot be built from are dropped and logged (counted
        by `_done`): one bad row must not stop every other row behind it."""
        try:
            return build_batch(items)
        except Exception:
            good: list[Row] = []
            for item in items:
                try:
                    build_batch([item])
                except Exception as exc:
                    log.error("writer: dropped a row it cannot write (%s): %r", exc, item)
                else:
                    good.append(item)
            return build_batch(good)

    def _done(self, seq: int | None, taken: int, written: int) -> None:
        with self._cond:
            if seq is not None:
                j = self.journal
                assert j is not None
                inherited = seq <= j.inherited_seq
                j.ack(seq)
                if inherited:
                    self._replayed += written
                else:
                    self._committed += written
                self._rejected += 0 if inherited else taken - written
            else:
                self._held = None
                self._inflight = 0
                self._committed += written
                self._rejected += taken - written
            self._batches += 1
            self._lag()  # drop the marks of what is committed
            if self._consecutive:
                log.warning("database writes resumed after %d failures", self._consecutive)
            self._consecutive = 0
            self._outage_since = None
            self._state = "idle"
            self._cond.notify_all()

    def _backoff(self, delay: float) -> bool:
        """Wait `delay` before the next attempt; with a journal and a long enough outage, move
        what memory holds to it every flush interval. True if the batch in flight moved."""
        flush_s = self.settings.flush_ms / 1000.0
        end = time.monotonic() + delay
        while True:
            with self._cond:
                remaining = end - time.monotonic()
                # Stopping with a journal: no more waiting, what is held goes there.
                if remaining <= 0 or (self._stopping and self.journal is not None):
                    return False
                self._cond.wait(min(remaining, flush_s))
                since = self._outage_since
            if (
                self.journal is not None
                and since is not None
                and time.monotonic() - since >= self.settings.spill_after_s
                and self._spill()
            ):
                return True

    def _spill(self) -> bool:
        """Move the rows held in memory (the batch in flight first) to the end of the journal.
        True if the batch in flight moved. A journal that cannot be written (a full disk)
        leaves them in memory, logged and counted."""
        j = self.journal
        if j is None:
            return False
        with self._cond:
            held = self._held or []
            items = [*held, *self._queue]
            if not items:
                return False
            self._queue.clear()
            self._held = None
            self._inflight = 0
            self._spilling = len(items)
        try:
            j.append(items, self.settings.batch_rows)
        except JournalError as exc:
            with self._cond:
                self._spilling = 0
                self._queue.extendleft(reversed(items))  # back in front, in order
                self._journal_errors += 1
                n = self._journal_errors
            if n == 1 or n % 10 == 0:
                log.error("journal write failed (%d times), rows stay in memory: %s", n, exc)
            return bool(held)
        with self._cond:
            self._spilling = 0
            self._spilled += len(items)
            self._cond.notify_all()  # room for put()
        return bool(held)

    def _spill_at_stop(self) -> None:
        """At a stop, after the thread ended, the rows the journal could not take (a full
        disk): into the journal with its reserve freed, else into the second location; what
        neither takes is logged as lost with its count (stop() returns it)."""
        j = self.journal
        with self._cond:
            items = [*(self._held or []), *self._queue]
        if j is None or not items:
            return
        errors: list[str] = []

        def reserved(rows: list[Row]) -> str:
            j.append_reserved(rows, self.settings.batch_rows)
            return str(j.path)

        def fallback(rows: list[Row]) -> str:
            assert self.journal_fallback is not None
            other = self.journal_fallback()
            try:
                other.append(rows, self.settings.batch_rows)
            finally:
                other.close()
            return str(other.path)

        ways = [reserved] + ([fallback] if self.journal_fallback is not None else [])
        for way in ways:
            try:
                where = way(items)
            except (JournalError, OSError) as exc:
                errors.append(describe(exc))
                continue
            with self._cond:
                self._queue.clear()
                self._held = None
                self._inflight = 0
                self._spilled += len(items)
            log.warning(
                "writer stopped: %d rows kept in %s, written at the next start", len(items), where
            )
            return
        log.critical(
            "writer stopped: %d rows LOST, no journal could take them (%s)",
            len(items),
            "; ".join(errors),
        )

    def _write(self, batch: Batch) -> None:
        # A batch not committed by its deadline (a database that stopped answering) fails
        # like an outage: its connection is closed, the batch kept and retried or journaled.
        with db_deadline(self.settings.write_timeout_s):
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
