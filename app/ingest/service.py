"""The live ingest: bus readers -> pipeline -> writer and hub, plus monitors and retention."""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import Sequence
from typing import Protocol, TypedDict

import can
from sqlalchemy import Engine

from eqgw.config import Settings
from eqgw.ingest.hub import EventHub
from eqgw.ingest.journal import JournalError, RowJournal, default_journal_dir
from eqgw.ingest.pipeline import IngestPipeline
from eqgw.ingest.state import LiveState
from eqgw.ingest.writer import BatchedWriter
from eqgw.jsontypes import JSONObject
from eqgw.store.engine import create_engine
from eqgw.store.migrate import upgrade_engine
from eqgw.store.queries import RestartUnitRow, restart_state
from eqgw.store.retention import prune
from eqgw.store.writes import VehicleInfo, ensure_vehicles
from eqgw.supervisor import Supervisor
from eqgw.tasks import cancel_and_wait, heals, in_thread_until_stopped

log = logging.getLogger(__name__)
# How long stop() waits for a bus's blocked driver calls before the final flush goes ahead.
SOURCE_STOP_S = 2.0

TICK_S = 1.0
HANDOVER_S = 0.1


class SourceStatus(Protocol):
    """A frame source's status (eqgw.bus.reader.BusStatus is one)."""

    def to_dict(self) -> JSONObject: ...


class FrameSource(Protocol):
    """What the service reads frames from (eqgw.bus.reader.BusReader is one)."""

    @property
    def name(self) -> str: ...
    async def start(self) -> None: ...
    async def stop(self, timeout: float = 10.0) -> None: ...
    async def get_batch(self, max_frames: int = 1000) -> list[can.Message]: ...
    def status(self) -> SourceStatus | JSONObject: ...


class HubReport(TypedDict):
    """The event hub's figures in `IngestService.status()`."""

    subscribers: int
    published: int
    dropped_subscribers: int


class PipelineReport(TypedDict):
    """The pipeline's figures in `IngestService.status()`."""

    frames: int
    records: int
    rows: int
    unmapped_frames: int
    other_dm1_transfers: int
    to_no_unit: int


class IngestStatus(TypedDict):
    """`IngestService.status()`: writer, hub, pipeline, bus and task figures (JSON)."""

    writer: JSONObject
    hub: HubReport
    pipeline: PipelineReport
    buses: list[JSONObject]
    tasks: list[JSONObject]


class IngestService:
    """Owns the engine, writer, hub, pipeline and bus readers of a running gateway."""

    def __init__(
        self,
        settings: Settings,
        *,
        engine: Engine | None = None,
        hub: EventHub | None = None,
        sources: Sequence[FrameSource] | None = None,
        retention: bool = True,
        supervisor: Supervisor | None = None,
        fleet_from_settings: bool = True,
    ) -> None:
        self.settings = settings
        # True: the settings' vehicles are written over the database's at start (a service of
        # its own); False: the database holds the fleet (eqgw serve: eqgw.fleet), and only
        # vehicles it lacks (a simulated fleet's) are added.
        self._fleet_from_settings = fleet_from_settings
        self._own_engine = engine is None
        self.engine = engine or create_engine(settings.database_url, deadlines=settings.db)
        self.hub = hub or EventHub(settings.hub.subscriber_queue)
        self.pipeline = IngestPipeline.from_settings(settings, self.hub)
        self.writer = BatchedWriter(self.engine, settings.writer)
        self._sources = list(sources) if sources is not None else None
        self._retention = retention
        # The read, monitor and retention loops: restarted with backoff when they fail.
        self.supervisor = supervisor or Supervisor()
        self._tasks: list[asyncio.Task[None]] = []
        self._readers: dict[str, asyncio.Task[None]] = {}  # bus name -> its read task
        self._bus_lock = asyncio.Lock()
        self._last_frame_mono = time.monotonic()
        self._started = False

    @property
    def live(self) -> LiveState:
        """Per-unit live state (latest values, open faults)."""
        return self.pipeline.live

    @property
    def sources(self) -> list[FrameSource]:
        return list(self._sources or [])

    async def start(self, *, migrate: bool = True) -> None:
        """Migrate, record the configured fleet, start the writer and read every bus."""
        if self._started:
            raise RuntimeError("ingest service already started")
        self._started = True
        if migrate:
            await asyncio.to_thread(upgrade_engine, self.engine)
        await asyncio.to_thread(self._sync_fleet)
        if self.settings.writer.journal and self.writer.journal is None:
            self.writer.journal = await asyncio.to_thread(self._open_journal)
        self.writer.start()
        try:
            restored = await self._replay_and_restore()
        except BaseException:
            await asyncio.to_thread(self.writer.stop, 5.0)  # nothing left running
            raise
        if restored:
            log.info("restored live state and open fault episodes of %d units", restored)
        from eqgw.bus.reader import BusReader, open_gate

        # Every bus of this gateway (and those a cluster lease adds later) opens through it.
        open_gate().limit = self.settings.bus_open_concurrency
        if self._sources is None:
            self._sources = [BusReader(cfg) for cfg in self.settings.buses]
        for src in self._sources:
            await src.start()
            self._readers[src.name] = self._start_reading(src)
        self._tasks.append(self.supervisor.start("ingest monitors", self._tick))
        if self._retention:
            self._tasks.append(self.supervisor.start("ingest retention", self._prune_loop))

    def _start_reading(self, src: FrameSource) -> asyncio.Task[None]:
        async def read() -> None:
            await self._read(src)

        return self.supervisor.start(f"ingest {src.name}", read)

    async def _replay_and_restore(self) -> int:
        # Rows an earlier run left in the journal are newer than the state in the database:
        # written first, so the live state and open episodes restored after include them.
        if self.writer.journal is not None and self.writer.journal.inherited_rows:
            n = self.writer.journal.inherited_rows
            if await asyncio.to_thread(self.writer.wait_replayed, 60.0):
                log.info("journal: wrote %d rows left by the previous run", n)
            else:
                log.warning("journal: rows left by the previous run not written yet; going on")
        return await asyncio.to_thread(self._restore)

    def _prepare_journal(self, journal: RowJournal) -> None:
        """The journal's reserve for a stop on a full disk, and its second location: rows an
        earlier stop left there are taken over (replayed first), and a stop the journal
        cannot take writes there."""
        url = self.settings.database_url
        writer = self.settings.writer
        want = writer.journal_reserve_bytes
        got = journal.reserve(want)
        if want and got >= want:
            log.info("journal: %d MB reserved in %s", got // 1_000_000, journal.reserve_path)
        fallback = writer.journal_fallback_dir
        if fallback:
            moved = journal.adopt_from(fallback, url)
            if moved:
                log.warning("journal: took over %d rows from %s", moved, fallback)

            def open_fallback() -> RowJournal:
                return RowJournal.open(fallback, url)

            self.writer.journal_fallback = open_fallback

    def _open_journal(self) -> RowJournal | None:
        url = self.settings.database_url
        chosen = self.settings.writer.journal_dir
        try:
            journal = RowJournal.open(chosen or default_journal_dir(url), url)
        except (JournalError, OSError) as exc:
            if chosen:  # configured: a folder that cannot be used is an error to fix
                raise
            # The default folder (the working directory) may not be writable: run as before,
            # rows held in memory only, and say so.
            log.error("no writer journal (%s): rows held during an outage stay in memory", exc)
            return None
        self._prepare_journal(journal)
        if journal.inherited_rows:
            log.warning(
                "journal: %d rows left unwritten by the previous run (%s)",
                journal.inherited_rows,
                journal.path,
            )
        return journal

    def _sync_fleet(self) -> None:
        rows: list[VehicleInfo] = [
            {"id": v.id, "name": v.display_name, "depot": v.depot} for v in self.settings.vehicles
        ]
        with self.engine.begin() as conn:
            ensure_vehicles(conn, rows, update_=self._fleet_from_settings)

    def _restore(self) -> int:
        """Live state and open episodes persisted before a restart, back into the pipeline."""
        with self.engine.connect() as conn:
            units = restart_state(conn, list(self.pipeline.bindings))
        return self.pipeline.restore(units)

    # -- buses added and removed at run time (one gateway of several on one PostgreSQL) -----

    def pause_all(self) -> None:
        """Take every configured bus out of the monitors before any is read: buses another
        gateway reads are mirrored (app/cluster), never ticked or persisted from here."""
        self.pipeline.active = set()

    async def add_source(self, src: FrameSource) -> None:
        """Start reading a bus: its units' state is reloaded from the database first (another
        gateway may have read it until now), then it is monitored and persisted from here."""
        async with self._bus_lock:
            if not self._started:
                raise RuntimeError("ingest service not started")
            if src.name in self._readers:
                raise ValueError(f"bus {src.name!r} is already read")
            rows = await asyncio.to_thread(self._restart_rows, [src.name])
            self.pipeline.reset_bus(src.name)
            self.pipeline.restore(rows)
            self.pipeline.register_units(src.name)
            if self.pipeline.active is not None:
                self.pipeline.active.add(src.name)
            if self._sources is None:
                self._sources = []
            self._sources.append(src)
            await src.start()
            self._readers[src.name] = self._start_reading(src)

    async def remove_source(self, name: str, *, flush_timeout: float | None = 5.0) -> bool:
        """Stop reading a bus (its reader first: nothing is read past this call); its live
        state is queued for the writer and, with `flush_timeout`, waited for, so the next
        reader starts from it. Its units stay in the live view, mirrored from then on.
        Returns whether everything was committed within the timeout."""
        return await self.remove_sources([name], flush_timeout=flush_timeout)

    async def remove_sources(
        self, names: Sequence[str], *, flush_timeout: float | None = 5.0
    ) -> bool:
        """`remove_source` for several buses at once (their readers stop concurrently)."""
        async with self._bus_lock:
            wanted = set(names)
            gone = [s for s in self._sources or [] if s.name in wanted]
            if not gone:
                return True
            self._sources = [s for s in self._sources or [] if s.name not in wanted]
            tasks = [t for n in wanted if (t := self._readers.pop(n, None)) is not None]
            await asyncio.gather(*(src.stop() for src in gone))
            if tasks:
                # A stopped source drains and ends its read loop; one that does not is cut.
                _, pending = await asyncio.wait(tasks, timeout=5.0)
                for task in pending:
                    task.cancel()
                await asyncio.gather(*pending, return_exceptions=True)
            for src in gone:
                if self.pipeline.active is not None:
                    self.pipeline.active.discard(src.name)
                self.pipeline.persist_bus(src.name)
            await self._handover()
            if flush_timeout is None:
                return True
            return await asyncio.to_thread(self.writer.flush, flush_timeout)

    def reading(self) -> list[str]:
        """Names of the buses this service reads now."""
        return sorted(self._readers)

    def _restart_rows(self, buses: list[str]) -> list[RestartUnitRow]:
        with self.engine.connect() as conn:
            return restart_state(conn, buses)

    async def stop(self, timeout: float = 30.0) -> int:
        """Stop reading, commit what was accepted, stop the writer; returns rows left unwritten."""
        # All at once, each bounded: a driver call still blocked after this is left behind
        # (logged), and the final flush below must not wait for it (nor for hundreds of buses
        # stopping one after another).
        await asyncio.gather(*(src.stop(timeout=SOURCE_STOP_S) for src in self._sources or []))
        readers = list(self._readers.values())
        self._readers.clear()
        for task in [*readers, *self._tasks]:
            await cancel_and_wait(task)
        self._tasks.clear()
        self.pipeline.finish()
        self._handover_final()
        left = await asyncio.to_thread(self.writer.stop, timeout)
        self.hub.close()
        if self._own_engine:
            self.engine.dispose()
        return left

    async def __aenter__(self) -> IngestService:
        await self.start()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.stop()

    # -- tasks -----------------------------------------------------------------------------

    async def _read(self, src: FrameSource) -> None:
        process_many = self.pipeline.process_many
        last_handover = time.monotonic()
        while True:
            batch = await src.get_batch(1000)
            if not batch:
                break  # source stopped
            self._last_frame_mono = time.monotonic()
            process_many(batch)
            now = time.monotonic()
            if self.pipeline.pending_rows >= 2048 or now - last_handover >= HANDOVER_S:
                await self._handover()
                last_handover = now

    async def _handover(self) -> None:
        rows = self.pipeline.take_rows()
        if not rows:
            return
        if self.settings.writer.overflow == "block":
            await self.writer.put_async(rows)
        elif not self.writer.offer(rows):
            log.warning(
                "writer full (%d rows held): %d new rows refused",
                self.writer.pending,
                len(rows),
            )

    def _handover_final(self) -> None:
        rows = self.pipeline.take_rows()
        if rows:
            self.writer.put(rows, timeout=5.0)

    async def _tick(self) -> None:
        while True:
            await asyncio.sleep(TICK_S)
            # Frame time, advanced by the wall time since the last frame: monitors see silence
            # whether the buses are live (wall-clock stamps) or replayed at pace (log stamps).
            clock = self.pipeline.clock
            if clock == float("-inf"):
                # Not a frame since the start: live buses stamp frames with the wall clock, so
                # units restored onto buses open but silent (a restart while the fleet is
                # parked) are judged against it.
                now = time.time()
                self._buses_opened(now)
                if self.pipeline.live.units:
                    self.pipeline.tick(now)
                    await self._handover()
                continue
            now = clock + (time.monotonic() - self._last_frame_mono)
            self._buses_opened(now)
            self.pipeline.tick(now)
            await self._handover()

    def _buses_opened(self, now: float) -> None:
        """Tell the pipeline which buses are open, so that units restored onto a bus that is
        open but silent go offline after the offline window (a frame tells it otherwise)."""
        for src in self._sources or []:
            if getattr(src, "state", None) == "open":
                self.pipeline.bus_opened(src.name, now)

    async def _prune_loop(self) -> None:
        r = self.settings.retention
        while True:
            try:
                # Cancelled (the gateway stops), the prune ends before its next transaction
                # and the stop waits for it: nothing of it runs once the engine is disposed.
                result = await in_thread_until_stopped(
                    lambda stop: prune(
                        self.engine,
                        raw_days=r.raw_days,
                        rollup_days=r.rollup_days,
                        rollup_days_by_width=r.rollup_days_by_width(),
                        batch_rows=r.batch_rows,
                        pause_s=0.05,
                        stop=stop,
                    )
                )
                if result.total:
                    log.info(
                        "retention: deleted %d rows in %d batches", result.total, result.batches
                    )
            except Exception as exc:  # the database may be away; try again next period
                if not heals(exc):
                    raise  # its supervisor stops it (a fatal one: the process)
                log.warning("retention failed: %s", exc)
            await asyncio.sleep(r.interval_s)

    def status(self) -> IngestStatus:
        """Writer, hub, pipeline and bus figures, for the API's health endpoint."""
        buses: list[JSONObject] = []
        for src in self._sources or []:
            st = src.status()
            buses.append(st if isinstance(st, dict) else st.to_dict())
        return {
            "writer": self.writer.status().as_dict(),
            "hub": {
                "subscribers": self.hub.subscribers,
                "published": self.hub.stats.published,
                "dropped_subscribers": self.hub.stats.dropped_subscribers,
            },
            "pipeline": {
                "frames": self.pipeline.stats.frames,
                "records": self.pipeline.stats.records,
                "rows": self.pipeline.stats.rows,
                "unmapped_frames": self.pipeline.stats.unmapped_frames,
                "other_dm1_transfers": sum(
                    b.decoder.stats.other_dm1_transfers for b in self.pipeline.bindings.values()
                ),
                "to_no_unit": self.pipeline.stats.to_no_unit,
            },
            "buses": buses,
            "tasks": [t.as_dict() for t in self.supervisor.status()],
        }
