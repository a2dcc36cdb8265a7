"""The central side of edge forwarding: uploaded frames -> the ingest pipeline -> one commit.

Each forwarder stream gets its own `IngestPipeline` (one bus, its own frame-time clock), the
path a replay takes: the same decoder, the same rows under the same natural keys, so a frame
stored twice is stored once. A batch's rows and the stream's new `acked_seq` are committed in
one transaction before the answer leaves, so an acknowledgement means stored. Sequence numbers
at or below `acked_seq` are answered without decoding them again; after a central restart the
stream's pipeline is rebuilt from the persisted live state and open fault episodes, as
`IngestService.start` does for live buses.

The streams' units are shown in the gateway's live view (`LiveState.attach`, one table per
bus: the pipeline that took the bus's latest batch), and at start the forwarded buses' units
are restored into it from the database. Each commit carries the live state as of the batch's
last frame, so a restart (or another central instance) continues from exactly what was
acknowledged. A forwarded unit is online only while recently heard (`UnitState.is_online`).
"""

from __future__ import annotations

import asyncio
import collections
import logging
import math
import time
from dataclasses import dataclass, field
from typing import Any

import can
from sqlalchemy import Engine

from eqgw.config import Settings
from eqgw.forward import repository as fq
from eqgw.forward.protocol import FLAG_ERROR, FLAG_EXTENDED, FLAG_REMOTE, MAX_DATA_BYTES
from eqgw.ingest.hub import EventHub
from eqgw.ingest.pipeline import BusBinding, IngestPipeline
from eqgw.ingest.state import LiveState
from eqgw.ingest.writer import build_batch
from eqgw.store.archive import last_groups
from eqgw.store.queries import restart_state
from eqgw.store.writes import UnitKey, VehicleInfo, load_unit_ids, write_batch

log = logging.getLogger(__name__)

# Pipelines kept in memory; an evicted stream's pipeline is rebuilt from the database.
MAX_STREAMS = 1024
# Why a frame of an upload is refused (not stored, yet acknowledged): its time is beyond the
# gateway's clock plus `forward.max_future_s`, or older than the raw retention.
REFUSED_REASONS = ("future", "too_old")
# Streams whose refusals are counted apart (in /metrics); the oldest counted are forgotten.
MAX_COUNTED_STREAMS = 10_000


class ForwardRefused(Exception):
    """An upload the central service will not take; `status` is the HTTP status to answer."""

    def __init__(self, status: int, detail: str) -> None:
        super().__init__(detail)
        self.status = status
        self.detail = detail


class _Stale(Exception):
    """The stream's acked_seq in the database is not the one this process decoded after."""

    def __init__(self, acked_seq: int) -> None:
        super().__init__(acked_seq)
        self.acked_seq = acked_seq


@dataclass(slots=True)
class Upload:
    """One batch from a forwarder (validated shape; frames still raw)."""

    stream: str
    vehicle: str
    bus: str
    equalizer_sas: tuple[int, ...]
    first_seq: int
    frames: list[tuple[float, int, str, int]]
    dropped: int = 0

    @property
    def last_seq(self) -> int:
        return self.first_seq + len(self.frames) - 1


@dataclass(slots=True)
class _Stream:
    vehicle_id: str
    bus: str
    acked_seq: int
    owner: int | None = None  # the ingest key (its lineage: rotations keep it) uploading it
    pipeline: IngestPipeline | None = None
    lock: asyncio.Lock = field(default_factory=asyncio.Lock)


def to_messages(frames: list[tuple[float, int, str, int]], bus: str) -> list[can.Message]:
    """Uploaded frames as `can.Message`s on `bus`; ForwardRefused(422) on a malformed one."""
    out = []
    for i, frame in enumerate(frames):
        ts, can_id, data_hex, flags = frame
        try:
            data = bytes.fromhex(data_hex)
        except ValueError:
            raise ForwardRefused(422, f"frames[{i}]: data is not hex") from None
        if not math.isfinite(ts) or not 0 <= can_id <= 0x1FFFFFFF or not 0 <= flags <= 7:
            raise ForwardRefused(422, f"frames[{i}]: bad timestamp, identifier or flags")
        if len(data) > MAX_DATA_BYTES:
            raise ForwardRefused(422, f"frames[{i}]: more than {MAX_DATA_BYTES} data bytes")
        out.append(
            can.Message(
                timestamp=ts,
                arbitration_id=can_id,
                data=data,
                is_extended_id=bool(flags & FLAG_EXTENDED),
                is_remote_frame=bool(flags & FLAG_REMOTE),
                is_error_frame=bool(flags & FLAG_ERROR),
                channel=bus,
                check=False,
            )
        )
    return out


class ForwardIngest:
    """Takes forwarders' uploads into the history of the central service."""

    def __init__(
        self,
        settings: Settings,
        engine: Engine,
        hub: EventHub | None = None,
        live: LiveState | None = None,
    ) -> None:
        self.settings = settings
        self.engine = engine
        self.hub = hub
        self.live = live  # the gateway's live view, where forwarded units are shown
        self._streams: collections.OrderedDict[str, _Stream] = collections.OrderedDict()
        self._units: dict[UnitKey, int] = {}
        self._write_engine = (
            engine.execution_options(sqlite_begin="IMMEDIATE")
            if engine.dialect.name == "sqlite"
            else engine
        )
        self.uploads = 0
        self.frames_stored = 0
        self.frames_duplicate = 0
        # Frames refused for their time, per (stream, vehicle, bus) and reason.
        self.refused: collections.OrderedDict[tuple[str, str, str], dict[str, int]] = (
            collections.OrderedDict()
        )

    def _check(self, up: Upload) -> None:
        vehicles = {v.id: v for v in self.settings.vehicles}
        if up.vehicle not in vehicles:
            raise ForwardRefused(404, f"unknown vehicle {up.vehicle!r}: not in the configuration")
        if up.bus != up.vehicle and not up.bus.startswith(up.vehicle + "/"):
            raise ForwardRefused(422, f"bus {up.bus!r} must be {up.vehicle!r} or start with it/")
        if any(b.name == up.bus for b in self.settings.buses):
            raise ForwardRefused(409, f"bus {up.bus!r} is read live by this service")

    async def _stream(self, up: Upload, owner: int | None) -> _Stream:
        st = self._streams.get(up.stream)
        if st is None:
            row = await asyncio.to_thread(self._load_stream, up.stream)
            st = self._streams.get(up.stream)  # another request may have loaded it meanwhile
            if st is None:
                if row is None:
                    st = _Stream(up.vehicle, up.bus, 0, owner)
                else:
                    st = _Stream(row["vehicle_id"], row["bus"], row["acked_seq"], row["key_id"])
                self._streams[up.stream] = st
                while len(self._streams) > MAX_STREAMS:
                    self._streams.popitem(last=False)
        self._streams.move_to_end(up.stream)
        if owner is not None:
            if st.owner is None:
                st.owner = owner
            elif st.owner != owner:
                raise ForwardRefused(
                    403,
                    f"stream {up.stream} belongs to another ingest key: a stream is "
                    "uploaded by one key (and the keys that replace it by rotation)",
                )
        if (st.vehicle_id, st.bus) != (up.vehicle, up.bus):
            raise ForwardRefused(
                409,
                f"stream {up.stream} feeds {st.vehicle_id} ({st.bus}); "
                "a buffer serves one vehicle bus",
            )
        return st

    def _load_stream(self, stream: str) -> dict[str, Any] | None:
        with self.engine.connect() as conn:
            return fq.get_stream(conn, stream)

    def _new_pipeline(self, up: Upload) -> IngestPipeline:
        """A one-bus pipeline that continues what the database holds of the bus."""
        vinfo: dict[str, VehicleInfo] = {
            v.id: {"id": v.id, "name": v.display_name, "depot": v.depot}
            for v in self.settings.vehicles
        }
        pipeline = IngestPipeline(
            [BusBinding(up.bus, up.vehicle, up.equalizer_sas)],
            vehicles=vinfo,
            hub=self.hub,
            monitor=self.settings.monitor,
            raw_archive=self.settings.raw_archive,
        )
        with self.engine.connect() as conn:
            pipeline.restore(restart_state(conn, [up.bus]))
            # Frames sharing a timestamp split across uploads: the next one continues its
            # group's indices (index 0 again would be stored over the first and lost).
            pipeline.continue_groups(last_groups(conn, up.bus))
        self._mark_forwarded(pipeline)
        return pipeline

    def _mark_forwarded(self, pipeline: IngestPipeline) -> None:
        for st in pipeline.live.units.values():
            st.fresh_within_s = self.settings.monitor.offline_after_s

    def _show(self, bus: str, vehicle_id: str, pipeline: IngestPipeline) -> None:
        if self.live is not None:
            self.live.attach(bus, vehicle_id, pipeline.live.units)

    async def restore_live(self) -> int:
        """Show the forwarded buses' units in the live view as the database holds them (at
        start, before any upload: offline, with their last values and last seen). Returns the
        units restored."""
        if self.live is None:
            return 0
        pipelines = await asyncio.to_thread(self._restored_pipelines)
        n = 0
        for (bus, vehicle_id), pipeline in pipelines.items():
            if bus not in self.live.attached:  # an upload may have come first
                self._show(bus, vehicle_id, pipeline)
                n += len(pipeline.live.units)
        return n

    def _restored_pipelines(self) -> dict[tuple[str, str], IngestPipeline]:
        vehicles = {v.id for v in self.settings.vehicles}
        read_live = {b.name for b in self.settings.buses}
        with self.engine.connect() as conn:
            buses: dict[str, str] = {}
            for row in fq.list_streams(conn):
                if row["vehicle_id"] in vehicles and row["bus"] not in read_live:
                    buses.setdefault(row["bus"], row["vehicle_id"])
            rows = restart_state(conn, list(buses))
        out = {}
        for bus, vehicle in buses.items():
            # Only to rebuild the units (no frame goes through it): the first upload makes
            # the stream's own pipeline, from the same rows.
            pipeline = IngestPipeline(
                [BusBinding(bus, vehicle)],
                monitor=self.settings.monitor,
                raw_archive=False,
            )
            pipeline.restore(r for r in rows if r["bus"] == bus)
            self._mark_forwarded(pipeline)
            out[(bus, vehicle)] = pipeline
        return out

    async def take(self, up: Upload, key_id: int | None = None) -> dict[str, Any]:
        """Store an upload; returns {stream, acked_seq, stored, duplicates, refused,
        refused_reasons} once committed. Frames refused for their time are acknowledged (the
        forwarder forgets them) and counted, never stored.
        `key_id` is the uploading key's lineage (its first id across rotations): a stream
        first uploaded by one key is refused (403) to any other."""
        self._check(up)
        st = await self._stream(up, key_id)
        async with st.lock:
            self.uploads += 1
            for _ in range(3):
                try:
                    return await self._take(up, st, key_id)
                except _Stale as stale:
                    # Another central instance stored part of this stream meanwhile: start
                    # over from what the database holds.
                    st.acked_seq = stale.acked_seq
                    st.pipeline = None
            raise ForwardRefused(503, "the stream is being uploaded elsewhere; retry")

    async def _take(self, up: Upload, st: _Stream, key_id: int | None) -> dict[str, Any]:
        if up.last_seq <= st.acked_seq or not up.frames:
            self.frames_duplicate += len(up.frames)
            return self._answer(up, st, 0, len(up.frames))
        # Frames at or below acked_seq were stored by an upload whose answer was lost;
        # a gap above it is the forwarder's full buffer dropping its oldest frames.
        skip = max(0, st.acked_seq + 1 - up.first_seq)
        msgs, refused = self._in_time(to_messages(up.frames[skip:], up.bus))
        if st.pipeline is None:
            st.pipeline = await asyncio.to_thread(self._new_pipeline, up)
        pipeline = st.pipeline
        units = pipeline.live.units
        before = {key: u.last_seen for key, u in units.items()}
        pipeline.process_many(msgs)
        received = time.time()
        for key, u in units.items():
            if u.fresh_within_s is None:  # heard for the first time
                u.fresh_within_s = self.settings.monitor.offline_after_s
            if u.last_seen != before.get(key):
                u.received_at = received
        self._show(up.bus, up.vehicle, pipeline)
        # The live state goes with every batch: a restart continues from what was acked.
        pipeline.persist_bus(up.bus)
        rows = pipeline.take_rows()
        try:
            await asyncio.to_thread(self._commit, up, rows, len(msgs), key_id, st.acked_seq)
        except _Stale:
            raise
        except Exception as exc:
            # The pipeline has seen frames that were not stored: rebuild it from the
            # database on the retry, so they are decoded again from a consistent state.
            st.pipeline = None
            log.warning("forwarded batch of %s not stored: %s", up.stream, exc)
            raise ForwardRefused(503, f"database unavailable, retry: {exc}") from exc
        st.acked_seq = up.last_seq
        self.frames_stored += len(msgs)
        self.frames_duplicate += skip
        if refused:
            self._count_refused(up, refused)
        return self._answer(up, st, len(msgs), skip, refused)

    def _in_time(self, msgs: list[can.Message]) -> tuple[list[can.Message], dict[str, int]]:
        """The frames whose time the gateway takes, and the count of the others by reason: a
        vehicle computer with a dead clock stamps 0 or the year 3000, which would be stored
        (and move the stream's clock) for good."""
        now = time.time()
        newest = now + self.settings.forward.max_future_s
        oldest = now - self.settings.retention.raw_days * 86400.0
        kept = [m for m in msgs if oldest <= m.timestamp <= newest]
        if len(kept) == len(msgs):
            return msgs, {}
        future = sum(1 for m in msgs if m.timestamp > newest)
        refused = {"future": future, "too_old": len(msgs) - len(kept) - future}
        return kept, {reason: n for reason, n in refused.items() if n}

    def _count_refused(self, up: Upload, refused: dict[str, int]) -> None:
        key = (up.stream, up.vehicle, up.bus)
        counts = self.refused.get(key)
        if counts is None:
            counts = self.refused[key] = dict.fromkeys(REFUSED_REASONS, 0)
            while len(self.refused) > MAX_COUNTED_STREAMS:
                self.refused.popitem(last=False)
            # Once per stream (and process): a dead clock refuses every frame it stamps.
            log.warning(
                "stream %s (%s, %s): %s refused for their time (more than %.0f s ahead of "
                "this gateway's clock, or older than the raw retention); is the vehicle "
                "computer's clock set?",
                up.stream,
                up.vehicle,
                up.bus,
                ", ".join(f"{n} frame(s) {reason}" for reason, n in refused.items()),
                self.settings.forward.max_future_s,
            )
        self.refused.move_to_end(key)
        for reason, n in refused.items():
            counts[reason] += n

    @staticmethod
    def _answer(
        up: Upload,
        st: _Stream,
        stored: int,
        duplicates: int,
        refused: dict[str, int] | None = None,
    ) -> dict[str, Any]:
        return {
            "stream": up.stream,
            "acked_seq": st.acked_seq,
            "stored": stored,
            "duplicates": duplicates,
            "refused": sum((refused or {}).values()),
            "refused_reasons": refused or {},
        }

    def _commit(
        self, up: Upload, rows: list[Any], frames: int, key_id: int | None, expected: int
    ) -> None:
        batch = build_batch(rows)
        for attempt in (1, 2):
            try:
                with self._write_engine.begin() as conn:
                    current = fq.locked_acked_seq(conn, up.stream)
                    if current != expected:
                        raise _Stale(current)
                    if not self._units:
                        self._units = load_unit_ids(conn)
                    result = write_batch(conn, batch, self._units)
                    fq.advance_stream(
                        conn,
                        stream=up.stream,
                        vehicle_id=up.vehicle,
                        bus=up.bus,
                        key_id=key_id,
                        acked_seq=up.last_seq,
                        frames=frames,
                        dropped=up.dropped,
                        now=time.time(),
                    )
            except KeyError:
                if attempt == 2:
                    raise
                self._units = {}  # a unit registered after our id cache was read
                continue
            self._units.update(result.unit_ids)
            return

    def status(self) -> dict[str, Any]:
        """Counters of this process."""
        return {
            "streams": len(self._streams),
            "uploads": self.uploads,
            "frames_stored": self.frames_stored,
            "frames_duplicate": self.frames_duplicate,
            "frames_refused": sum(sum(c.values()) for c in self.refused.values()),
        }
