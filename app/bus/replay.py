"""Recorded CAN logs as a frame source, interchangeable with a live bus."""

from __future__ import annotations

import asyncio
import gc
import gzip
import logging
import os
import sys
from collections.abc import AsyncIterator, Iterator
from pathlib import Path
from typing import Any

import can
from can.io.generic import BinaryIOMessageReader, MessageReader, TextIOMessageReader
from can.io.player import MESSAGE_READERS

from eqgw.bus import mf4
from eqgw.bus.errors import LogFileError
from eqgw.bus.mf4_salvage import Mf4Salvage, Mf4SalvageError, open_salvage, quiet_asammdf
from eqgw.describe import describe

log = logging.getLogger(__name__)

# What `open_log_reader` gives: python-can's reader, or the salvage of an MF4 cut short.
LogReader = MessageReader | Mf4Salvage


def salvage_notice(reader: object) -> str | None:
    """The one line said of a truncated MF4 read to its cut ("truncated MF4: recovered N
    frames up to ..."), None for any other reader."""
    return reader.summary() if isinstance(reader, Mf4Salvage) else None


def blf_truncation(reader: Any, path: str | os.PathLike[str]) -> str | None:
    """Why a BLF log read to its end is incomplete: the file is shorter than its header says
    (python-can's reader stops at the cut without a word). None when complete or not a BLF."""
    declared = getattr(reader, "file_size", None)
    if not isinstance(declared, int) or declared <= 0:
        return None
    actual = os.path.getsize(path)
    if actual < declared:
        return f"{path}: truncated: the BLF header says {declared} bytes, the file has {actual}"
    return None


def _quiet_unraisable(unraisable: Any, previous: Any = sys.unraisablehook) -> None:
    """Drop the destructor noise of a log reader that failed half-way through its own
    constructor (asammdf's MDF4.__del__ on a truncated file: AttributeError '_file')."""
    module = getattr(getattr(unraisable, "object", None), "__module__", "") or ""
    if module.startswith("asammdf"):
        return
    previous(unraisable)


def _open_mf4_salvage(path: Path) -> Mf4Salvage | None:
    """The salvage reader of an MF4 file cut short (None when it is whole)."""
    try:
        return open_salvage(path)
    except Mf4SalvageError as exc:
        raise LogFileError(f"{path}: truncated MF4: nothing to recover: {exc}") from exc
    except ImportError as exc:
        raise LogFileError(
            f'{path}: cannot read: {describe(exc)} (MF4 needs `pip install "eqgw[mf4]"`)'
        ) from exc
    except Exception as exc:
        # A file this broken may fail anywhere in asammdf's block classes.
        raise LogFileError(f"{path}: cannot read: {describe(exc)}") from exc


def open_log_reader(path: str | os.PathLike[str], *, absolute_asc: bool = False) -> LogReader:
    """python-can's reader for a log file (any format it reads, gzip-compressed text logs
    too), or a `LogFileError` in one line.

    The file is opened here, not in the reader, so a reader that fails while opening (a
    corrupt BLF header, an MF4 cut short) still closes it; its half-built object is collected
    here with its destructor's complaint kept off stderr (asammdf's MDF4.__del__).
    An MF4 file cut short (a power cut) is read by `eqgw.bus.mf4_salvage` up to the cut
    instead: asammdf cannot open it; `salvage_notice(reader)` says what was recovered.
    `absolute_asc`: ASC timestamps as wall-clock time (live replay), not relative.
    """
    path = Path(path)
    if not path.is_file():
        raise LogFileError(f"{path}: no such log file")
    suffixes = [s.lower() for s in path.suffixes]
    compressed = suffixes[-1:] == [".gz"]
    fmt = (suffixes[-2:-1] if compressed else suffixes[-1:]) or [""]
    reader_type = MESSAGE_READERS.get(fmt[0])
    if reader_type is None:
        raise LogFileError(f"{path}: unknown log format {''.join(suffixes) or '(none)'}")
    if fmt[0] == ".mf4":
        mf4.load()  # python-can's MF4Reader says itself where asammdf is missing
    if fmt[0] == ".mf4" and not compressed:
        salvage = _open_mf4_salvage(path)
        if salvage is not None:
            return salvage
    kwargs: dict[str, Any] = {}
    if fmt[0] == ".asc" and absolute_asc:
        kwargs["relative_timestamp"] = False
    previous = sys.unraisablehook
    sys.unraisablehook = lambda u: _quiet_unraisable(u, previous)
    try:
        if not issubclass(reader_type, TextIOMessageReader | BinaryIOMessageReader):
            # .db readers open files themselves and cannot read compressed ones.
            if compressed:
                raise LogFileError(f"{path}: {fmt[0]} logs cannot be gzip-compressed")
            try:
                return reader_type(path)
            except Exception as exc:
                exc.__traceback__ = None  # its frames hold the half-built reader
                raise LogFileError(f"{path}: cannot read: {describe(exc)}") from exc
        text = issubclass(reader_type, TextIOMessageReader)
        mode = "rt" if text else "rb"
        try:
            file: Any = gzip.open(path, mode) if compressed else open(path, mode)
        except OSError as exc:
            raise LogFileError(f"{path}: cannot open: {describe(exc)}") from exc
        try:
            # asammdf logs what it finds wrong in a file (with a traceback) before raising.
            with quiet_asammdf():
                return reader_type(file=file, **kwargs)
        except Exception as exc:
            file.close()
            exc.__traceback__ = None  # its frames hold the half-built reader
            raise LogFileError(f"{path}: cannot read: {describe(exc)}") from exc
    finally:
        gc.collect()
        sys.unraisablehook = previous


class LogReplaySource:
    """Yields the frames of a log file python-can reads (.log, .asc, .blf, .trc, .csv, .gz)."""

    def __init__(
        self,
        path: str | os.PathLike[str],
        *,
        channel_map: dict[str, str] | None = None,
        default_channel: str | None = None,
        yield_every: int = 500,
    ) -> None:
        if yield_every < 1:
            raise ValueError("yield_every must be at least 1")
        self.path = Path(path)
        # Log channels ("can0", 1, ...) to bus names; unmapped ones keep their text.
        self.channel_map = dict(channel_map or {})
        # For frames the format records no channel for (.csv, some .trc).
        self.default_channel = default_channel
        self.yield_every = yield_every
        self.frames = 0

    def _open(self) -> LogReader:
        # Live frames carry wall-clock time; ASC files are replayed the same way.
        return open_log_reader(self.path, absolute_asc=True)

    def _channel_of(self, msg: can.Message) -> str | None:
        if msg.channel is None or msg.channel == "":
            return self.default_channel
        key = str(msg.channel)
        return self.channel_map.get(key, key)

    def __iter__(self) -> Iterator[can.Message]:
        reader = self._open()
        with reader:
            frames = iter(reader)
            while True:
                try:
                    msg = next(frames)
                except StopIteration:
                    notice = salvage_notice(reader)
                    if notice is not None:
                        log.warning("%s: %s", self.path, notice)
                    return
                except Exception as exc:
                    raise LogFileError(
                        f"{self.path}: unreadable after frame {self.frames}: {describe(exc)}"
                    ) from exc
                msg.channel = self._channel_of(msg)
                self.frames += 1
                yield msg

    async def __aiter__(self) -> AsyncIterator[can.Message]:
        # Local files read fast enough in the loop; yielding every few hundred frames keeps a
        # long replay from starving the other tasks.
        for count, msg in enumerate(self, start=1):
            yield msg
            if count % self.yield_every == 0:
                await asyncio.sleep(0)
