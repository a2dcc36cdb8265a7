"""CAN log files made from archived frames with python-can's writers, a page at a time.

`LogExport` takes frames in pages (`write`) and gives the file's bytes as they are made, so an
export of any length holds one page in memory:

- candump (`can.CanutilsLogWriter`, `candump -L` lines) and ASC (`can.ASCWriter`) are text
  written to a buffer emptied after every page: the bytes of a page go out before the next
  page is read.
- BLF (`can.BLFWriter`) and MF4 (`can.MF4Writer`, through asammdf) are finished at their end
  (BLF writes its header, with the file's size and times, last; MF4 writes its whole
  structure when saved): they are written to a file in a private temporary folder, then read
  out in chunks (`read`). Memory stays bounded; the disk holds the file until `close`.

What reads back exactly (python-can's readers, `eqgw replay`): identifiers, the extended
flag, DLC, data and order always; timestamps to the bit in BLF and MF4, to the microsecond in
candump and ASC (their text carries six decimals: the SocketCAN and candump resolution, so
a frame stamped by a bus or read from a candump log comes back to the bit).
"""

from __future__ import annotations

import io
import math
import shutil
import tempfile
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any, Protocol

import can

from eqgw.bus import mf4

# Format name -> file suffix (as `eqgw replay` and python-can's LogReader recognise them).
FORMATS: dict[str, str] = {"candump": ".log", "asc": ".asc", "blf": ".blf", "mf4": ".mf4"}
# What an HTTP answer of each format is.
MEDIA_TYPES: dict[str, str] = {
    "candump": "text/plain; charset=utf-8",
    "asc": "text/plain; charset=utf-8",
    "blf": "application/octet-stream",
    "mf4": "application/octet-stream",
}
# Bytes read at a time from a finished BLF or MF4 file.
CHUNK = 1 << 20


class ExportError(Exception):
    """A log file cannot be made (an unknown format, MF4 without asammdf)."""


class LoggedFrame(Protocol):
    """What an export needs of a frame (eqgw.store.archive.Frame has it)."""

    @property
    def ts(self) -> float: ...
    @property
    def can_id(self) -> int: ...
    @property
    def is_extended(self) -> bool: ...
    @property
    def is_remote(self) -> bool: ...
    @property
    def is_error(self) -> bool: ...
    @property
    def data(self) -> bytes: ...


ChannelFrame = tuple[int, LoggedFrame]  # (log channel, frame)


def format_of(path: str | Path) -> str | None:
    """The export format a file name asks for by its suffix (None if none)."""
    suffix = Path(path).suffix.lower()
    return next((name for name, ext in FORMATS.items() if ext == suffix), None)


class _TextBuffer(io.StringIO):
    """A text writer's file whose text is taken after each page; the writer's `stop()`
    closes its file, which must not lose what the last page and the trailer wrote."""

    def close(self) -> None:
        pass

    def take(self) -> bytes:
        text = self.getvalue()
        self.seek(0)
        self.truncate(0)
        return text.encode()


def _message(channel: int, f: LoggedFrame) -> can.Message:
    data = bytes(f.data)
    return can.Message(
        timestamp=f.ts,
        arbitration_id=f.can_id,
        is_extended_id=f.is_extended,
        is_remote_frame=f.is_remote,
        is_error_frame=f.is_error,
        is_fd=len(data) > 8,
        dlc=len(data),
        data=data,
        channel=channel,
        is_rx=True,
    )


class LogExport:
    """One log file of archived frames, made page by page (see the module's docstring).

    `write(page)` -> the bytes ready now; `finish()` -> the last ones (a text trailer); then,
    for BLF and MF4, `read(CHUNK)` until it gives b""; `close()` in every case."""

    def __init__(self, fmt: str) -> None:
        if fmt not in FORMATS:
            raise ExportError(f"unknown log format {fmt!r}; one of {', '.join(FORMATS)}")
        self.format = fmt
        self.frames = 0
        self._text: _TextBuffer | None = None
        self._dir: Path | None = None
        self._file: Any = None
        self._started = False
        self._finished = False
        self._writer: Any
        if fmt == "candump":
            self._text = _TextBuffer()
            self._writer = can.CanutilsLogWriter(self._text)
        elif fmt == "asc":
            self._text = _TextBuffer()
            self._writer = can.ASCWriter(self._text)
        else:
            if fmt == "mf4" and not mf4_available():
                raise ExportError("MF4 needs asammdf: pip install 'eqgw[mf4]'")
            self._dir = Path(tempfile.mkdtemp(prefix="eqgw-export-"))
            path = self._dir / f"export{FORMATS[fmt]}"
            self._writer = can.BLFWriter(path) if fmt == "blf" else _PagedMF4Writer(path)
            self._path = path

    def write(self, page: Sequence[ChannelFrame]) -> bytes:
        """Add a page of frames, in time order; returns the file's bytes made so far (text
        formats), or b"" (BLF and MF4: the file is read out after `finish`)."""
        if self._finished:
            raise ExportError("the export is finished")
        if page and not self._started:
            self._start(page[0][1].ts)
        if isinstance(self._writer, _PagedMF4Writer):
            self._writer.write_page(page)
        else:
            write = self._writer.on_message_received
            for channel, f in page:
                write(_message(channel, f))
        self.frames += len(page)
        return self._text.take() if self._text is not None else b""

    def _start(self, first_ts: float) -> None:
        self._started = True
        if self.format == "asc":
            # ASC times are relative to the trigger block's start, which the file dates to
            # the millisecond: a start on a whole second makes each time exact again when read.
            self._writer.log_event("eqgw export", timestamp=float(math.floor(first_ts)))

    def finish(self) -> bytes:
        """End the file: returns its last bytes (text formats); BLF and MF4 are then read
        with `read`."""
        if self._finished:
            return b""
        self._finished = True
        self._writer.stop()
        if self._text is not None:
            return self._text.take()
        self._file = self._path.open("rb")
        return b""

    def read(self, size: int = CHUNK) -> bytes:
        """The next bytes of a finished BLF or MF4 file (b"" at its end, and for text)."""
        if self._file is None:
            return b""
        chunk: bytes = self._file.read(size)
        return chunk

    def close(self) -> None:
        """Remove the temporary file (also when the export was not finished)."""
        if self._file is not None:
            self._file.close()
            self._file = None
        if not self._finished:
            self._finished = True
            try:
                self._writer.stop()
            except Exception:  # a writer given nothing or cut short: the file goes anyway
                pass
        if self._dir is not None:
            shutil.rmtree(self._dir, ignore_errors=True)
            self._dir = None


def export_chunks(pages: Iterable[Sequence[ChannelFrame]], export: LogExport) -> Iterable[bytes]:
    """The bytes of a whole export, page after page (the export is closed at the end)."""
    try:
        for page in pages:
            chunk = export.write(page)
            if chunk:
                yield chunk
        tail = export.finish()
        if tail:
            yield tail
        while chunk := export.read():
            yield chunk
    finally:
        export.close()


def mf4_available() -> bool:
    """Whether python-can can write MF4 here (asammdf installed; loaded by this call)."""
    return mf4.load()


class _PagedMF4Writer(can.MF4Writer):
    """python-can's MF4 writer, given a page of frames at once: one asammdf `extend` per page
    with the arrays its `on_message_received` would have made a frame at a time. Frame by
    frame, an extend costs about 120 us and keeps about 270 B until the file is saved: a
    month of one vehicle (5 million frames) would take ten minutes and over a gigabyte.
    Remote and error frames, which the archive does not hold, go the writer's own way."""

    def write_page(self, page: Sequence[ChannelFrame]) -> None:
        import numpy as np
        from can.io.mf4 import STD_DTYPE
        from can.util import len2dlc

        data = [(ch, f) for ch, f in page if not (f.is_remote or f.is_error)]
        for ch, f in page:
            if f.is_remote or f.is_error:
                self.on_message_received(_message(ch, f))
        if not data:
            return
        n = len(data)
        rec = np.zeros(n, dtype=STD_DTYPE)
        lengths = [len(f.data) for _, f in data]
        rec["CAN_DataFrame.BusChannel"] = [ch for ch, _ in data]
        rec["CAN_DataFrame.ID"] = [f.can_id for _, f in data]
        rec["CAN_DataFrame.IDE"] = [f.is_extended for _, f in data]
        rec["CAN_DataFrame.DataLength"] = lengths
        rec["CAN_DataFrame.DLC"] = [len2dlc(n) if n > 8 else n for n in lengths]
        rec["CAN_DataFrame.EDL"] = [n > 8 for n in lengths]
        padded = b"".join(bytes(f.data).ljust(64, b"\0") for _, f in data)
        rec["CAN_DataFrame.DataBytes"] = np.frombuffer(padded, dtype=np.uint8).reshape(n, 64)
        stamps = np.array([f.ts for _, f in data], dtype="<f8") - self._start_time
        self.last_timestamp = max(self.last_timestamp, data[-1][1].ts)
        self._mdf.extend(0, [(stamps, None), (rec, None)])
