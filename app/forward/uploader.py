"""The forwarder: a bus read into the local buffer, and the buffer uploaded when the central
service answers (at-least-once: frames leave the buffer only once acknowledged as stored)."""

from __future__ import annotations

import asyncio
import contextlib
import gzip
import json
import logging
from collections.abc import Callable
from dataclasses import asdict, dataclass
from typing import Any

import httpx

from eqgw.bus.config import BusConfig
from eqgw.bus.reader import BusReader
from eqgw.describe import describe
from eqgw.forward.buffer import FrameBuffer
from eqgw.forward.protocol import MAX_DATA_BYTES, flags_of, is_equalizer_frame
from eqgw.supervisor import FatalError, Supervisor
from eqgw.tasks import Backoff, heals

log = logging.getLogger(__name__)


@dataclass(slots=True)
class UploadSettings:
    """Where and how uploads go."""

    url: str  # the central API base, e.g. https://central.example/api/v1
    key: str
    vehicle: str
    bus: str  # the bus name frames are filed under centrally
    equalizer_sas: tuple[int, ...] = (0x1E,)
    batch_frames: int = 2000
    gzip: bool = True
    timeout_s: float = 30.0
    backoff_initial_s: float = 0.5
    backoff_max_s: float = 30.0
    idle_poll_s: float = 1.0  # with nothing buffered, look again this often


@dataclass(slots=True)
class UploaderStatus:
    """What the uploader has done."""

    state: str  # idle, uploading, backoff, stopped
    uploads: int
    frames_acked: int
    duplicates: int
    # Acknowledged but not stored by the central service: their time was refused.
    frames_refused: int
    failures: int
    consecutive_failures: int
    last_error: str | None
    last_ack_at: float | None

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)


class UploadRefused(Exception):
    """The central service answered with an error (status and detail). A 401 or 403 (the
    forwarder's key unknown, revoked, or not allowed this vehicle) does not heal by retrying:
    `heals` is False and the process ends with that one line (`fatal`); its frames stay in
    the buffer for the next start. Any other answer is retried with backoff."""

    fatal = True

    def __init__(self, status: int, detail: str) -> None:
        super().__init__(f"HTTP {status}: {detail}")
        self.status = status
        self.heals = status not in (401, 403)


class Uploader:
    """Uploads the buffer's oldest frames in batches; backs off while the central is away."""

    def __init__(
        self,
        buffer: FrameBuffer,
        settings: UploadSettings,
        *,
        transport: httpx.AsyncBaseTransport | None = None,
    ) -> None:
        self.buffer = buffer
        self.settings = settings
        self._transport = transport
        self._wake = asyncio.Event()
        self._state = "idle"
        self._uploads = 0
        # Counted by the buffer as it forgets them (`FrameBuffer.ack`): a status read the
        # moment the buffer is empty counts every frame that left it.
        self._forgotten_before = buffer.acknowledged()[0]
        self._duplicates = 0
        self._refused = 0
        self._failures = 0
        self._consecutive = 0
        self._last_error: str | None = None

    def wake(self) -> None:
        """New frames are buffered (called from the loop)."""
        self._wake.set()

    def status(self) -> UploaderStatus:
        forgotten, acked_at = self.buffer.acknowledged()
        return UploaderStatus(
            state=self._state,
            uploads=self._uploads,
            frames_acked=forgotten - self._forgotten_before,
            duplicates=self._duplicates,
            frames_refused=self._refused,
            failures=self._failures,
            consecutive_failures=self._consecutive,
            last_error=self._last_error,
            last_ack_at=acked_at,
        )

    def _body(self, rows: list[tuple[int, float, int, bytes, int]]) -> dict[str, Any]:
        s = self.settings
        return {
            "stream": self.buffer.stream,
            "vehicle": s.vehicle,
            "bus": s.bus,
            "equalizer_sas": list(s.equalizer_sas),
            "first_seq": rows[0][0],
            "dropped": self.buffer.dropped,
            "frames": [[ts, can_id, data.hex(), flags] for _, ts, can_id, data, flags in rows],
        }

    def _batch(self) -> list[tuple[int, float, int, bytes, int]]:
        """The oldest frames, cut at the first gap in their numbers (one upload is one run of
        consecutive sequence numbers)."""
        rows = self.buffer.peek(self.settings.batch_frames)
        for i in range(1, len(rows)):
            if rows[i][0] != rows[i - 1][0] + 1:
                return rows[:i]
        return rows

    async def _post(self, client: httpx.AsyncClient, body: dict[str, Any]) -> dict[str, Any]:
        raw = json.dumps(body, separators=(",", ":")).encode()
        headers = {"Authorization": f"Bearer {self.settings.key}"}
        headers["Content-Type"] = "application/json"
        if self.settings.gzip:
            raw = await asyncio.to_thread(gzip.compress, raw, 5)
            headers["Content-Encoding"] = "gzip"
        r = await client.post("/ingest/frames", content=raw, headers=headers)
        if r.status_code != 200:
            try:
                detail = str(r.json().get("detail", r.text))
            except ValueError:
                detail = r.text[:200]
            raise UploadRefused(r.status_code, detail)
        answer: dict[str, Any] = r.json()
        return answer

    async def run(self) -> None:
        """Upload until cancelled."""
        s = self.settings
        backoff = Backoff(s.backoff_initial_s, s.backoff_max_s)
        base = s.url.rstrip("/")
        async with httpx.AsyncClient(
            base_url=base, timeout=s.timeout_s, transport=self._transport
        ) as client:
            try:
                while True:
                    rows = await asyncio.to_thread(self._batch)
                    if not rows:
                        self._state = "idle"
                        self._wake.clear()
                        with contextlib.suppress(TimeoutError):
                            async with asyncio.timeout(s.idle_poll_s):
                                await self._wake.wait()
                        continue
                    self._state = "uploading"
                    try:
                        answer = await self._post(client, self._body(rows))
                    except (httpx.HTTPError, UploadRefused, ValueError) as exc:
                        if not heals(exc):
                            raise  # its supervisor ends the process, in one line
                        self._fail(exc, backoff.delay)
                        self._state = "backoff"
                        # Jitter keeps a fleet coming back online from arriving at once.
                        await asyncio.sleep(backoff.next())
                        continue
                    backoff.reset()
                    self._recover()
                    # Never forget beyond what this batch sent, whatever the answer says.
                    acked = min(int(answer["acked_seq"]), rows[-1][0])
                    self._uploads += 1
                    self._duplicates += int(answer.get("duplicates", 0))
                    self._note_refused(answer)
                    await asyncio.to_thread(self.buffer.ack, acked)
            finally:
                self._state = "stopped"

    def _note_refused(self, answer: dict[str, Any]) -> None:
        """Frames the central service acknowledged without storing them (their time was
        refused): forgotten like the others, counted and logged, never sent again."""
        refused = int(answer.get("refused", 0))
        if refused <= 0:
            return
        first = self._refused == 0
        self._refused += refused
        if first or self._refused // 1000 != (self._refused - refused) // 1000:
            reasons = answer.get("refused_reasons") or {}
            log.warning(
                "the central service refused %d frame(s) for their time (%s; %d so far): "
                "is this computer's clock set?",
                refused,
                ", ".join(f"{reason}: {n}" for reason, n in reasons.items()) or "no reason",
                self._refused,
            )

    def _fail(self, exc: BaseException, delay: float) -> None:
        self._failures += 1
        self._consecutive += 1
        self._last_error = describe(exc)
        if self._consecutive == 1 or self._consecutive % 20 == 0:
            log.warning(
                "upload failed (%d in a row, %d frames buffered), retrying in %.1f s: %s",
                self._consecutive,
                self.buffer.rows,
                delay,
                self._last_error,
            )

    def _recover(self) -> None:
        if self._consecutive:
            log.warning("uploads resumed after %d failures", self._consecutive)
        self._consecutive = 0
        self._last_error = None


class Forwarder:
    """One vehicle bus read into a buffer (`BusReader`), and an `Uploader` emptying it."""

    def __init__(
        self,
        bus: BusConfig,
        buffer: FrameBuffer,
        upload: UploadSettings,
        *,
        all_frames: bool = False,
        reader: BusReader | None = None,
        transport: httpx.AsyncBaseTransport | None = None,
        on_fatal: Callable[[FatalError], None] | None = None,
    ) -> None:
        self.bus = bus
        self.buffer = buffer
        self.all_frames = all_frames
        self.reader = reader or BusReader(bus)
        self.uploader = Uploader(buffer, upload, transport=transport)
        self.frames_read = 0
        self.frames_kept = 0
        self.frames_malformed = 0  # longer than a J1939 frame: never uploaded
        # The read and upload loops: a failure (the disk full, the buffer locked) is logged
        # and the loop restarted with backoff; one that cannot heal calls on_fatal.
        longest = min(10.0, upload.backoff_max_s)
        self.supervisor = Supervisor(backoff=(min(0.5, longest), longest), on_fatal=on_fatal)
        self._read_task: asyncio.Task[None] | None = None

    async def start(self) -> None:
        await self.reader.start()
        self._read_task = self.supervisor.start("read", self._read)
        self.supervisor.start("upload", self.uploader.run)

    async def stop(self) -> None:
        """Stop reading (what was read is buffered) and uploading."""
        await self.reader.stop()
        # The read loop ends by itself once the bus is drained; the uploader is cancelled.
        if self._read_task is not None:
            with contextlib.suppress(asyncio.CancelledError, TimeoutError):
                async with asyncio.timeout(10.0):
                    await asyncio.shield(self._read_task)
        await self.supervisor.stop()
        self._read_task = None

    async def __aenter__(self) -> Forwarder:
        await self.start()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.stop()

    async def _read(self) -> None:
        sas = frozenset(self.bus.equalizer_sas)
        keep_all = self.all_frames
        while True:
            batch = await self.reader.get_batch(5000)
            if not batch:
                return  # the reader stopped
            self.frames_read += len(batch)
            rows = []
            for msg in batch:
                flags = flags_of(msg)
                can_id = msg.arbitration_id
                if len(msg.data) > MAX_DATA_BYTES:
                    # CAN FD or a corrupt frame: the central service would refuse the upload.
                    self.frames_malformed += 1
                elif keep_all or is_equalizer_frame(can_id, flags, sas):
                    rows.append((msg.timestamp, can_id, bytes(msg.data), flags))
            if rows:
                await asyncio.to_thread(self.buffer.add, rows)
                self.frames_kept += len(rows)  # counted once buffered
                self.uploader.wake()

    def status(self) -> dict[str, Any]:
        """Bus, buffer, upload and task figures. `dropped`: frames read and not kept, by the
        buffer (full, or unable to write) and by the bus reader (its queue full meanwhile)."""
        bus = self.reader.status().to_dict()
        buffer = self.buffer.status().as_dict()
        return {
            "bus": bus,
            "frames_read": self.frames_read,
            "frames_kept": self.frames_kept,
            "dropped": buffer["dropped"] + int(bus.get("drops", 0)),
            "frames_malformed": self.frames_malformed,
            "buffer": buffer,
            "upload": self.uploader.status().as_dict(),
            "tasks": {t.name: t.as_dict() for t in self.supervisor.status()},
        }
