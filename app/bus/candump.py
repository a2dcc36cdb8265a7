"""candump logs (`candump -L`, and plain `candump -ta` output) read line by line.

Reads what python-can's `CanutilsLogReader` reads, frame for frame (the tests compare both on
every fixture log), but a line it cannot read is recorded with its number and reading goes on
(python-can stops the whole file on the first one). Stricter than python-can where its reading
is wrong: an odd number of hex digits (`ABC`, which python-can reads as `AB 0C`) and a
timestamp that is not a finite number are bad lines.
"""

from __future__ import annotations

import gzip
import math
import os
import re
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import IO, Any, NamedTuple

import can

# The frame tuple the decoder reads: (ts, channel, can_id, data, extended, remote, error).
Frame = tuple[float, str | None, int, bytes, bool, bool, bool]


class FrameRecord(NamedTuple):
    """A `Frame` whose fields also carry the names of `can.Message`'s attributes, so the
    ingest pipeline reads it as it reads a message (without building one per line)."""

    timestamp: float
    channel: str | None
    arbitration_id: int
    data: bytes
    is_extended_id: bool
    is_remote_frame: bool
    is_error_frame: bool


_record = tuple.__new__  # FrameRecord from a tuple literal, without NamedTuple's __new__ call

CAN_ERR_FLAG = 0x20000000
CAN_ERR_BUSERROR = 0x00000080
CANFD_BRS = 0x01
CANFD_ESI = 0x02
BAD_LINES_KEPT = 100
_DIRECTIONS = frozenset({"R", "T", "r", "t"})  # candump -L: received / transmitted
_NOT_DATA = ("#", "R", "r")  # CAN FD and remote frames: the careful path
_IDS_CACHED = 65536

# Plain candump output: "  can0  18FFD61E   [8]  D8 09 B0 13 BA 7C C8 7D", optionally
# preceded by "(1763700040.900000)" (-ta); remote frames end "remote request".
_PLAIN = re.compile(
    r"^(?:\((?P<ts>[^)]*)\)\s+)?(?P<chan>\S+)\s+(?P<id>[0-9A-Fa-f]{1,8})\s+"
    r"\[(?P<dlc>\d{1,2})\]\s*(?P<rest>.*)$"
)
_HEX_BYTES = re.compile(r"^(?:[0-9A-Fa-f]{2}(?:\s+|$))*$")


class LineError(ValueError):
    """A line that is not a frame."""


@dataclass(slots=True)
class _Parsed:
    """One frame with every attribute python-can's reader gives its `can.Message`."""

    ts: float
    channel: str | None
    can_id: int
    data: bytes
    extended: bool
    remote: bool
    error: bool
    fd: bool = False
    brs: bool = False
    esi: bool = False
    dlc: int = 0
    rx: bool = True


# The longest candump line of a frame is ~200 characters (a 64-byte CAN FD frame on a long
# interface name); a longer line is no frame, and is read in pieces of this size and skipped,
# so a corrupt file with a line of hundreds of MB costs no more memory than a normal one.
MAX_LINE_CHARS = 4096


def _bounded_lines(file: IO[str], limit: int = MAX_LINE_CHARS) -> Iterator[str | None]:
    """The file's lines; None for a line longer than `limit` (read through, never held)."""
    readline = file.readline
    while line := readline(limit):
        if len(line) < limit or line[-1] == "\n":
            yield line
            continue
        while (rest := readline(limit)) and rest[-1] != "\n":
            pass
        yield None


@dataclass(slots=True)
class CandumpReader:
    """Frames of a candump log (`.log`, `.log.gz`, `.txt`); bad lines are kept, not raised."""

    path: str | os.PathLike[str]
    bad_lines: int = 0
    # (line number, reason) of the first BAD_LINES_KEPT bad lines.
    bad: list[tuple[int, str]] = field(default_factory=list)
    # Lines of plain candump output without a timestamp (candump without -L or -t).
    untimed_plain: int = 0
    frames: int = 0

    def _open(self) -> IO[str]:
        if str(self.path).lower().endswith(".gz"):
            return gzip.open(self.path, "rt", encoding="ascii", errors="replace")
        return open(self.path, encoding="ascii", errors="replace")

    def _bad(self, lineno: int, reason: str) -> None:
        self.bad_lines += 1
        if len(self.bad) < BAD_LINES_KEPT:
            self.bad.append((lineno, reason))

    def __iter__(self) -> Iterator[FrameRecord]:
        """(ts, channel, can_id, data, extended, remote, error) per frame, in file order."""
        fromhex = bytes.fromhex
        # A log repeats a few hundred identifiers and a few channels: parse each once.
        ids: dict[str, tuple[int, bool] | None] = {}
        channels: dict[str, str] = {}
        limit = MAX_LINE_CHARS
        lineno = 0
        with self._open() as file:
            readline = file.readline
            while line := readline(limit):  # (inlined _bounded_lines: this is the hot loop)
                lineno += 1
                if len(line) == limit and line[-1] != "\n":
                    while (rest := readline(limit)) and rest[-1] != "\n":
                        pass
                    self._bad(lineno, f"line longer than {limit} characters")
                    continue
                parts = line.split()
                # The candump -L line of a classic data frame: the path nearly every line takes.
                n = len(parts)
                if n == 3 or (n == 4 and parts[3] in _DIRECTIONS):
                    ts_s, chan, frame = parts[0], parts[1], parts[2]
                    cid, sep, data = frame.partition("#")
                    if sep:
                        if cid in ids:
                            ident = ids[cid]
                        else:
                            ident = _data_frame_id(cid)
                            if len(ids) < _IDS_CACHED:
                                ids[cid] = ident
                        if (
                            ident is not None
                            and ts_s[0] == "("
                            and ts_s[-1] == ")"
                            and data[:1] not in _NOT_DATA
                        ):
                            try:
                                ts = float(ts_s[1:-1])
                                payload = fromhex(data)
                            except ValueError:
                                pass
                            else:
                                if ts - ts == 0.0:  # finite: NaN and infinities give NaN
                                    channel = channels.get(chan)
                                    if channel is None:
                                        channel = str(int(chan)) if chan.isdigit() else chan
                                        channels[chan] = channel
                                    self.frames += 1
                                    yield _record(
                                        FrameRecord,
                                        (ts, channel, ident[0], payload, ident[1], False, False),
                                    )
                                    continue
                p = self._parse_counted(lineno, line) if parts else None
                if p is not None:
                    yield FrameRecord(
                        p.ts, p.channel, p.can_id, p.data, p.extended, p.remote, p.error
                    )

    def messages(self) -> Iterator[can.Message]:
        """The frames as python-can's `CanutilsLogReader` gives them (`can.Message`s)."""
        with self._open() as file:
            for lineno, line in enumerate(_bounded_lines(file), start=1):
                if line is None:
                    self._bad(lineno, f"line longer than {MAX_LINE_CHARS} characters")
                    continue
                p = self._parse_counted(lineno, line) if line.strip() else None
                if p is not None:
                    yield _message(p)

    def _parse_counted(self, lineno: int, line: str) -> _Parsed | None:
        """A non-blank line by the careful parser, counted as a frame, or as a bad line (then
        None)."""
        try:
            p = self._parse_slow(line)
        except LineError as exc:
            self._bad(lineno, str(exc))
            return None
        self.frames += 1
        return p

    def _parse_slow(self, line: str) -> _Parsed:
        parts = line.split()
        if len(parts) in (3, 4) and "#" in parts[2]:
            return _parse_l(parts)
        plain = _PLAIN.match(line.strip())
        if plain is not None:
            if plain["ts"] is None:
                self.untimed_plain += 1
                raise LineError("plain candump output without a timestamp")
            return _parse_plain(plain)
        raise LineError("not a candump line")


def _data_frame_id(cid: str) -> tuple[int, bool] | None:
    """(identifier, extended) of a -L data frame's id field; None for the careful path (short
    or malformed ids, error frames)."""
    if not 3 <= len(cid) <= 8 or not _is_hex(cid):
        return None
    can_id = int(cid, 16)
    if can_id & CAN_ERR_FLAG:
        return None
    return can_id & 0x1FFFFFFF, len(cid) > 3


def _timestamp(text: str) -> float:
    try:
        ts = float(text)
    except ValueError:
        raise LineError(f"timestamp {text!r} is not a number") from None
    if not math.isfinite(ts):
        raise LineError(f"timestamp {text!r} is not a finite number")
    return ts


def _parse_l(parts: list[str]) -> _Parsed:
    """A `candump -L` line: `(ts) channel id#data` with an optional ` R`/` T` direction."""
    rx = True
    if len(parts) == 4:
        if parts[3].lower() not in ("r", "t"):
            raise LineError("not a candump -L line")
        rx = parts[3].lower() == "r"
    ts_s, chan, frame = parts[:3]
    if ts_s[:1] != "(" or ts_s[-1:] != ")":
        raise LineError("no (timestamp)")
    ts = _timestamp(ts_s[1:-1])
    cid, _, data = frame.partition("#")
    if not 1 <= len(cid) <= 8 or not _is_hex(cid):
        raise LineError(f"identifier {cid!r} is not 1-8 hex digits")
    can_id = int(cid, 16)
    fd = brs = esi = False
    if data[:1] == "#":
        if len(data) < 2 or not _is_hex(data[1]):
            raise LineError("CAN FD flags missing")
        fd = True
        flags = int(data[1], 16)
        brs, esi = bool(flags & CANFD_BRS), bool(flags & CANFD_ESI)
        data = data[2:]
    remote = data[:1] in ("R", "r")
    if remote:
        if len(data) > 1 and not data[1:].isdigit():
            raise LineError(f"remote frame length {data[1:]!r} is not a number")
        dlc = int(data[1:]) if len(data) > 1 else 0
        payload = b""
    else:
        if len(data) % 2:
            raise LineError(f"odd number of hex digits in {data!r}")
        try:
            payload = bytes.fromhex(data)
        except ValueError:
            raise LineError(f"data {data!r} is not hex") from None
        dlc = len(payload)
    channel = str(int(chan)) if chan.isdigit() else chan
    if can_id & CAN_ERR_FLAG and can_id & CAN_ERR_BUSERROR:
        # python-can keeps only the timestamp of an error frame.
        return _Parsed(ts, None, 0, b"", True, False, True, rx=True)
    return _Parsed(
        ts,
        channel,
        can_id & 0x1FFFFFFF,
        payload,
        len(cid) > 3,
        remote,
        False,
        fd,
        brs,
        esi,
        dlc,
        rx,
    )


def _parse_plain(m: re.Match[str]) -> _Parsed:
    """Plain candump output with an absolute timestamp (`candump -ta`)."""
    ts = _timestamp(m["ts"])
    cid = m["id"]
    can_id = int(cid, 16)
    dlc = int(m["dlc"])
    rest = m["rest"].strip()
    chan = m["chan"]
    channel = str(int(chan)) if chan.isdigit() else chan
    if rest.lower().startswith("remote request"):
        return _Parsed(ts, channel, can_id & 0x1FFFFFFF, b"", len(cid) > 3, True, False, dlc=dlc)
    hex_part = rest.split("'")[0].replace("ERRORFRAME", "").strip()  # -a ASCII, -e errors
    if not _HEX_BYTES.match(hex_part):
        raise LineError(f"data {hex_part!r} is not hex bytes")
    payload = bytes.fromhex(hex_part)
    if len(payload) != dlc:
        raise LineError(f"[{dlc}] but {len(payload)} data bytes")
    if can_id & CAN_ERR_FLAG:
        return _Parsed(ts, None, 0, b"", True, False, True)
    return _Parsed(ts, channel, can_id, payload, len(cid) > 3, False, False, fd=dlc > 8, dlc=dlc)


def _is_hex(text: str) -> bool:
    return all(c in "0123456789abcdefABCDEF" for c in text)


def _message(p: _Parsed) -> can.Message:
    if p.error:
        return can.Message(timestamp=p.ts, is_error_frame=True)
    channel: Any = p.channel
    if channel is not None and channel.isdigit():
        channel = int(channel)  # python-can's reader gives numeric channels as ints
    return can.Message(
        timestamp=p.ts,
        arbitration_id=p.can_id,
        is_extended_id=p.extended,
        is_remote_frame=p.remote,
        is_fd=p.fd,
        is_rx=p.rx,
        bitrate_switch=p.brs,
        error_state_indicator=p.esi,
        dlc=p.dlc,
        data=None if p.remote else p.data,
        channel=channel,
    )


def is_candump_path(path: str | os.PathLike[str]) -> bool:
    """Whether a file name is one this reader takes (`.log`, `.log.gz`, `.txt`)."""
    name = str(path).lower()
    return name.endswith((".log", ".log.gz", ".txt"))
