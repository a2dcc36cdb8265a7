"""Recorded CAN logs as a frame source, interchangeable with a live bus."""

from __future__ import annotations

import asyncio
import contextlib
import gzip
import os
import struct
import sys
from collections.abc import AsyncIterator, Iterator
from pathlib import Path
from typing import Any

import can
from can.io.generic import BinaryIOMessageReader, MessageReader, TextIOMessageReader
from can.io.player import MESSAGE_READERS

from app.bus.errors import LogFileError
from app.bus.reader import describe


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

    def _open(self) -> MessageReader:
        if not self.path.is_file():
            raise LogFileError(f"{self.path}: no such log file")
        suffixes = [s.lower() for s in self.path.suffixes]
        compressed = suffixes[-1:] == [".gz"]
        fmt = (suffixes[-2:-1] if compressed else suffixes[-1:]) or [""]
        reader_type = MESSAGE_READERS.get(fmt[0])
        if reader_type is None:
            raise LogFileError(f"{self.path}: unknown log format {''.join(suffixes) or '(none)'}")
        kwargs: dict[str, Any] = {}
        if fmt[0] == ".asc":
            # Live frames carry wall-clock time; ASC files are replayed the same way.
            kwargs["relative_timestamp"] = False
        if not issubclass(reader_type, TextIOMessageReader | BinaryIOMessageReader):
            # .db and .mf4 readers open files themselves and cannot read compressed ones.
            if compressed:
                raise LogFileError(f"{self.path}: {fmt[0]} logs cannot be gzip-compressed")
            try:
                return reader_type(self.path)
            except Exception as exc:
                raise LogFileError(f"{self.path}: cannot read: {describe(exc)}") from exc
        # Opening the file here, not in the reader, lets a failing reader constructor (a
        # corrupt BLF header) still close it.
        text = issubclass(reader_type, TextIOMessageReader)
        mode = "rt" if text else "rb"
        try:
            file: Any = gzip.open(self.path, mode) if compressed else open(self.path, mode)
        except OSError as exc:
            raise LogFileError(f"{self.path}: cannot open: {describe(exc)}") from exc
        try:
            return reader_type(file=file, **kwargs)
        except Exception as exc:
            file.close()
            raise LogFileError(f"{self.path}: cannot read: {describe(exc)}") from exc

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


class LogFrame:
    """A frame read from a log by another process: the attributes of `can.Message` that the
    ingest reads, without the cost of building a `can.Message`."""

    __slots__ = (
        "arbitration_id",
        "channel",
        "data",
        "is_error_frame",
        "is_extended_id",
        "is_remote_frame",
        "timestamp",
    )

    def __init__(
        self,
        timestamp: float,
        arbitration_id: int,
        data: bytes,
        channel: Any,
        is_extended_id: bool,
        is_remote_frame: bool,
        is_error_frame: bool,
    ) -> None:
        self.timestamp = timestamp
        self.arbitration_id = arbitration_id
        self.data = data
        self.channel = channel
        self.is_extended_id = is_extended_id
        self.is_remote_frame = is_remote_frame
        self.is_error_frame = is_error_frame


_END = b"end"
_LEN = struct.Struct("<I")


def _read_log_child_main() -> None:
    """The reader process (`python -c`): python-can's LogReader, frames written to stdout
    in length-prefixed pickled batches of tuples; a failure as a (stage, reason, frames)."""
    import pickle

    path, batch = sys.argv[1], int(sys.argv[2])
    out = sys.stdout.buffer
    frames = 0

    def send(payload: bytes) -> None:
        # Blocks while the pipe is full: the parent's pace bounds the memory used.
        out.write(_LEN.pack(len(payload)))
        out.write(payload)

    def fail(stage: str, exc: BaseException) -> None:
        with contextlib.suppress(OSError):
            send(pickle.dumps((stage, describe(exc), frames)))
            out.flush()

    try:
        reader = can.LogReader(path)
    except Exception as exc:
        fail("open", exc)
        return
    rows: list[tuple[Any, ...]] = []
    try:
        for m in reader:
            rows.append(
                (
                    m.timestamp,
                    m.arbitration_id,
                    bytes(m.data),
                    m.channel,
                    m.is_extended_id,
                    m.is_remote_frame,
                    m.is_error_frame,
                )
            )
            frames += 1
            if len(rows) >= batch:
                send(pickle.dumps(rows, pickle.HIGHEST_PROTOCOL))
                rows = []
        if rows:
            send(pickle.dumps(rows, pickle.HIGHEST_PROTOCOL))
        send(_END)
        out.flush()
    except (BrokenPipeError, ConnectionResetError):
        pass  # the parent stopped reading
    except Exception as exc:
        with contextlib.suppress(OSError):
            if rows:  # what was read before the failure is delivered first
                send(pickle.dumps(rows, pickle.HIGHEST_PROTOCOL))
        fail("read", exc)
    finally:
        stop = getattr(reader, "stop", None)
        if stop is not None:
            with contextlib.suppress(Exception):
                stop()


def read_log_in_child(path: str | os.PathLike[str], *, batch: int = 4096) -> Iterator[LogFrame]:
    """The frames of a log as `can.LogReader` reads them, parsed in a child process.

    On a machine with more than one core the parse (python-can's reader, a few microseconds a
    frame) runs beside the decode and the database writes instead of taking turns with them
    under one GIL; handing a frame over costs about a microsecond. A missing, unknown or
    unreadable log raises `LogFileError`, with the frames read before the failure delivered
    first, as an in-process reader would. Closing the generator stops the child.
    """
    import pickle
    import subprocess

    # A plain interpreter, not multiprocessing: nothing of the caller's __main__ is imported.
    root = str(Path(__file__).resolve().parent.parent.parent)
    env = {
        **os.environ,
        "PYTHONPATH": os.pathsep.join(filter(None, [root, os.environ.get("PYTHONPATH")])),
    }
    proc = subprocess.Popen(
        [
            sys.executable,
            "-c",
            "from app.bus.replay import _read_log_child_main; _read_log_child_main()",
            os.fspath(path),
            str(batch),
        ],
        stdin=subprocess.DEVNULL,
        stdout=subprocess.PIPE,
        env=env,
    )
    stdout = proc.stdout
    assert stdout is not None
    try:
        while True:
            head = stdout.read(_LEN.size)
            if len(head) < _LEN.size:
                code = proc.wait()
                raise LogFileError(
                    f"{path}: the log reader process ended unexpectedly (exit code {code})"
                )
            payload = stdout.read(_LEN.unpack(head)[0])
            if payload == _END:
                return
            rows = pickle.loads(payload)
            if isinstance(rows, tuple):
                stage, reason, read = rows
                if stage == "open":
                    raise LogFileError(f"cannot read {path}: {reason}")
                raise LogFileError(f"{path}: unreadable after frame {read}: {reason}")
            for row in rows:
                yield LogFrame(*row)
    finally:
        stdout.close()
        if proc.poll() is None:
            proc.terminate()
        proc.wait(timeout=10)
