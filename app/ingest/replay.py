"""Load a CAN log into the history: `eqgw replay FILE --vehicle BUS-101`."""

from __future__ import annotations

import logging
import time
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import asdict, dataclass, field
from itertools import islice
from pathlib import Path
from typing import Protocol

import can
from sqlalchemy.exc import SQLAlchemyError

from eqgw.bus.candump import CandumpReader, is_candump_path
from eqgw.bus.errors import LogFileError
from eqgw.bus.replay import blf_truncation, open_log_reader, salvage_notice
from eqgw.config import Settings
from eqgw.describe import describe
from eqgw.ingest.pipeline import BusBinding, IngestPipeline
from eqgw.ingest.writer import BatchedWriter, WriterStatus
from eqgw.jsontypes import JSONObject
from eqgw.protocol.decode import FrameLike, lookalike_summary
from eqgw.store import archive
from eqgw.store.engine import create_engine
from eqgw.store.migrate import upgrade_engine
from eqgw.store.writes import VehicleInfo

log = logging.getLogger(__name__)

# Rows handed to the writer at once; big enough to amortise its lock, small enough to stream.
HANDOVER_ROWS = 2048
# Frames read from the log per pipeline call (the pipeline's loop runs without a call per frame).
CHUNK_FRAMES = 1024
_TEXT_LOGS = (".asc", ".log", ".csv", ".trc", ".txt")


class ReplayError(Exception):
    """The replay cannot start: bad vehicle mapping, unreadable log.

    `exit_code`: 2 when the file is no log that can be read (as `eqgw decode` exits), else 1.
    """

    def __init__(self, message: str, *, exit_code: int = 1) -> None:
        super().__init__(message)
        self.exit_code = exit_code


# The decoder's counts summed over the buses (`eqgw.protocol.decode.DecodeStats`), and
# `lookalike`: frames from addresses not decoded, per address.
DecodeCounts = dict[str, int | dict[str, int]]


def _count(counts: DecodeCounts, key: str, n: int) -> None:
    have = counts.get(key, 0)
    counts[key] = (have if isinstance(have, int) else 0) + n


class _Progress(Protocol):
    """A progress bar (tqdm's)."""

    def update(self, n: int) -> object: ...
    def close(self) -> None: ...


@dataclass(slots=True)
class ReplaySummary:
    """What a replay read and wrote."""

    path: str
    frames: int
    records: int
    rows: int
    seconds: float
    unmapped_frames: int
    decode: DecodeCounts
    writer: WriterStatus
    units: list[JSONObject] = field(default_factory=list)
    # candump lines that are not frames (skipped, reading went on): count and the first ones.
    bad_lines: int = 0
    bad: list[tuple[int, str]] = field(default_factory=list)
    # Why reading stopped before the end of the file (a truncated or corrupt binary log).
    read_error: str | None = None
    # A log cut short whose frames before the cut were read (a truncated MF4): what was
    # recovered ("truncated MF4: recovered N frames up to ..."); the frames are stored.
    truncated: str | None = None
    # The equalizer addresses decoded (every bus's).
    decoded_sas: list[int] = field(default_factory=list)
    # Control, parameter and request records on a bus where no unit was heard (not stored).
    to_no_unit: int = 0

    @property
    def frames_per_s(self) -> float:
        return self.frames / self.seconds if self.seconds > 0 else 0.0

    @property
    def records_per_s(self) -> float:
        return self.records / self.seconds if self.seconds > 0 else 0.0

    def as_dict(self) -> dict[str, object]:
        out: dict[str, object] = asdict(self)
        out["frames_per_s"] = self.frames_per_s
        out["records_per_s"] = self.records_per_s
        return out

    def text(self) -> str:
        w = self.writer
        new = ", ".join(f"{k} {v}" for k, v in sorted(w.inserted.items()) if v)
        units = ", ".join(f"{u['bus']}#{u['sa']}" for u in self.units)
        lines = [
            f"replayed {self.path}: {self.frames} frames, {self.records} records in "
            f"{self.seconds:.2f} s ({self.frames_per_s:,.0f} frames/s, "
            f"{self.records_per_s:,.0f} records/s)",
            f"  units: {units or 'none'}",
            f"  new rows: {new or 'none (already in the history)'}",
            f"  malformed frames: {self.decode.get('malformed', 0)}, "
            f"unmapped channel frames: {self.unmapped_frames}",
        ]
        if self.to_no_unit:
            lines.append(
                f"  frames to an equalizer on a bus where none was heard: {self.to_no_unit} "
                "(not stored: traffic to the equalizers never makes a unit)"
            )
        lookalike = self.decode.get("lookalike")
        if isinstance(lookalike, dict) and lookalike:
            counts = {int(k): v for k, v in lookalike.items()}
            lines.append("  " + lookalike_summary(counts, self.decoded_sas))
        if self.bad_lines:
            shown = "; ".join(f"line {n}: {reason}" for n, reason in self.bad[:10])
            more = f"; {self.bad_lines - 10} more" if self.bad_lines > 10 else ""
            lines.append(f"  malformed lines: {self.bad_lines} ({shown}{more})")
        if self.read_error:
            lines.append(f"  NOT READ TO THE END: {self.read_error}")
        if w.failures:
            lines.append(f"  database failures retried: {w.failures} (last: {w.last_error})")
        if w.pending_rows:
            lines.append(f"  NOT WRITTEN: {w.pending_rows} rows (database unavailable)")
        return "\n".join(lines)


def parse_vehicle_map(specs: Sequence[str]) -> dict[str | None, str]:
    """`BUS-101` (every channel) or `can0=BUS-101` entries -> {log channel or None: vehicle}."""
    if not specs:
        raise ReplayError("give --vehicle ID, or --vehicle CHANNEL=ID per log channel")
    out: dict[str | None, str] = {}
    for spec in specs:
        channel, sep, vehicle = spec.rpartition("=")
        key = channel.strip() if sep else None
        vehicle = vehicle.strip()
        if not vehicle or (sep and not key):
            raise ReplayError(f"bad --vehicle {spec!r}: use ID or CHANNEL=ID")
        if key in out:
            raise ReplayError(f"channel {key or '(all)'} is mapped twice")
        out[key] = vehicle
    if None in out and len(out) > 1:
        raise ReplayError("--vehicle ID (all channels) cannot be combined with CHANNEL=ID")
    return out


def bindings_for(
    vehicle_map: dict[str | None, str],
    settings: Settings,
    sas: Sequence[int] | None = None,
) -> tuple[list[BusBinding], dict[str | None, str]]:
    """Buses of a replay and the log channel -> bus routing.

    A configured bus of the vehicle (matched by channel, or the vehicle's only bus) lends its
    name and equalizer addresses, so replayed and live history land on the same units.
    `sas` (`--sa`) names the equalizer addresses instead of the configuration or 30.
    """
    bindings: dict[str, BusBinding] = {}
    route: dict[str | None, str] = {}
    for channel, vehicle in vehicle_map.items():
        buses = [b for b in settings.buses if b.vehicle_id == vehicle]
        match = next((b for b in buses if channel is not None and b.channel == channel), None)
        if match is None and len(buses) == 1:
            match = buses[0]
        if match is not None:
            name, unit_sas, order = match.name, tuple(match.equalizer_sas), match.request_byte_order
        else:
            name = vehicle if channel is None else f"{vehicle}/{channel}"
            unit_sas, order = (0x1E,), "lsb"
        if sas:
            unit_sas = tuple(sas)
        if name not in bindings:
            bindings[name] = BusBinding(name, vehicle, unit_sas, order)
        route[channel] = name
    return list(bindings.values()), route


def _estimate_frames(path: Path) -> int | None:
    """Line count of a text log (a progress-bar total); None for binary formats."""
    if path.suffix.lower() not in _TEXT_LOGS:
        return None
    n = 0
    with path.open("rb") as fh:
        while chunk := fh.read(1 << 20):
            n += chunk.count(b"\n")
    return n


def _messages(path: Path, notices: list[str] | None = None) -> Iterator[can.Message]:
    """The frames of a log python-can reads; a truncated MF4's notice goes to `notices`."""
    try:
        # ASC: the times the log's trigger block dates, not seconds from its start (the
        # history is kept by wall-clock time, and an exported ASC replays to the same times).
        reader = open_log_reader(path, absolute_asc=True)
    except LogFileError as exc:
        raise ReplayError(str(exc), exit_code=2) from exc
    try:
        yield from reader
        truncated = blf_truncation(reader, path)
        if truncated is not None:
            raise EOFError(truncated)
        notice = salvage_notice(reader)
        if notice is not None and notices is not None:
            notices.append(notice)
    finally:
        stop = getattr(reader, "stop", None)
        if stop is not None:
            stop()


def replay_file(
    path: str | Path,
    vehicles: Sequence[str] | dict[str | None, str],
    settings: Settings | None = None,
    *,
    database_url: str | None = None,
    progress: bool = False,
    migrate: bool = True,
    messages: Iterable[can.Message] | None = None,
    sas: Sequence[int] | None = None,
) -> ReplaySummary:
    """Replay a log into the database; replaying the same log again adds nothing."""
    settings = settings or Settings()
    path = Path(path)
    if messages is None and not path.is_file():
        raise ReplayError(f"no such log file: {path}")
    vmap = vehicles if isinstance(vehicles, dict) else parse_vehicle_map(vehicles)
    bindings, route = bindings_for(vmap, settings, sas)
    vinfo: dict[str, VehicleInfo] = {
        v.id: {"id": v.id, "name": v.display_name, "depot": v.depot} for v in settings.vehicles
    }
    pipeline = IngestPipeline(
        bindings,
        channel_map=route,
        vehicles=vinfo,
        monitor=settings.monitor,
        raw_archive=settings.raw_archive,
    )
    engine = create_engine(database_url or settings.database_url, deadlines=settings.db)
    writer = BatchedWriter(engine, settings.writer)
    bar: _Progress | None = None
    it: Iterator[FrameLike] | None = None
    try:
        if migrate:
            upgrade_engine(engine)
        writer.start()
        if progress:
            from tqdm import tqdm

            bar = tqdm(
                total=_estimate_frames(path) if messages is None else None,
                unit=" frames",
                unit_scale=True,
                desc=path.name,
            )
        candump: CandumpReader | None = None
        notices: list[str] = []
        if messages is not None:
            source: Iterable[FrameLike] = messages
        elif is_candump_path(path):
            # A bad line is counted and skipped (python-can's reader ends the file there). Its
            # frame records carry what the pipeline reads of a can.Message (the tests compare
            # them with python-can's messages on every fixture log), at a fraction of the cost.
            candump = CandumpReader(path)
            source = iter(candump)
        else:
            source = _messages(path, notices)
        started = time.perf_counter()
        process_many = pipeline.process_many
        it = iter(source)
        read_error: str | None = None
        while True:
            try:
                chunk = list(islice(it, CHUNK_FRAMES))
            except ReplayError:
                raise
            except Exception as exc:
                read_error = f"unreadable after {pipeline.stats.frames} frames: {describe(exc)}"
                break
            if not chunk:
                break
            process_many(chunk)
            if pipeline.pending_rows >= HANDOVER_ROWS:
                writer.put(pipeline.take_rows())
            if bar is not None:
                bar.update(len(chunk))
        pipeline.finish()
        writer.put(pipeline.take_rows())
        writer.flush()
        # The minutes replayed are packed now rather than by the next gateway that runs
        # (should this fail, they wait in raw_recent for it: nothing is lost).
        try:
            archive.compact(engine)
        except (SQLAlchemyError, archive.ArchiveError) as exc:
            log.warning("the replayed frames are not packed yet: %s", describe(exc))
        seconds = time.perf_counter() - started
    finally:
        close = getattr(it, "close", None)
        if close is not None:
            close()  # the log reader closes its file with its generator, also on an error
        if bar is not None:
            bar.close()
        writer.stop()
        engine.dispose()
    # Frames the pipeline kept from the decoder count as the decoder's "ignored".
    skipped = pipeline.stats.skipped_frames
    decode: DecodeCounts = {"frames": skipped, "ignored": skipped}
    lookalike: dict[int, int] = {}
    for b in bindings:
        for k, v in b.decoder.stats.as_dict().items():
            if isinstance(v, int):
                _count(decode, k, v)
        for sa, n in b.decoder.stats.lookalike.items():
            lookalike[sa] = lookalike.get(sa, 0) + n
    decode["lookalike"] = {str(sa): n for sa, n in sorted(lookalike.items())}
    if candump is not None:
        if candump.untimed_plain and not candump.frames:
            raise ReplayError(
                f"{path}: plain candump output without timestamps; record with "
                "`candump -L` (or `candump -ta`)",
                exit_code=2,
            )
        if candump.bad_lines and not candump.frames and read_error is None:
            raise ReplayError(
                f"{path}: not a candump log (no line of {candump.bad_lines} is a frame)",
                exit_code=2,
            )
        _count(decode, "malformed", candump.bad_lines)
    return ReplaySummary(
        path=str(path),
        frames=pipeline.stats.frames,
        records=pipeline.stats.records,
        rows=pipeline.stats.rows,
        seconds=seconds,
        unmapped_frames=pipeline.stats.unmapped_frames,
        decode=decode,
        writer=writer.status(),
        units=[s.ref.to_dict() for s in pipeline.live.units.values()],
        bad_lines=candump.bad_lines if candump is not None else 0,
        bad=list(candump.bad) if candump is not None else [],
        read_error=read_error,
        truncated=notices[0] if notices else None,
        to_no_unit=pipeline.stats.to_no_unit,
        decoded_sas=sorted({sa for b in bindings for sa in b.equalizer_sas}),
    )
