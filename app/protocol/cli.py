"""`eqgw decode` and `eqgw dbc`: the protocol core on the command line."""

from __future__ import annotations

import argparse
import os
import sys
from collections.abc import Iterator
from typing import TYPE_CHECKING

if TYPE_CHECKING:  # the command's own imports are lazy (a CLI starts fast)
    from eqgw.bus.replay import LogReader
    from eqgw.protocol.records import Record

RECORD_NAMES = (
    "status",
    "heartbeat",
    "voltages",
    "battery_states",
    "dm1",
    "component_id",
    "software_id",
    "control",
    "parameters",
    "request",
)


def parse_sas(text: str) -> list[int]:
    """`30,31` (decimal or 0x..) -> source addresses, for `--sa`."""
    sas: list[int] = []
    for part in text.split(","):
        part = part.strip()
        if not part:
            continue
        try:
            value = int(part, 0)
        except ValueError as exc:
            raise argparse.ArgumentTypeError(f"not a source address: {part!r}") from exc
        if not 0 <= value <= 253:
            raise argparse.ArgumentTypeError(f"source address {value} is not 0..253")
        sas.append(value)
    if not sas:
        raise argparse.ArgumentTypeError("give at least one source address")
    return sas


def _parse_only(text: str) -> list[str]:
    names = [n.strip() for n in text.split(",") if n.strip()]
    unknown = [n for n in names if n not in RECORD_NAMES]
    if unknown:
        raise argparse.ArgumentTypeError(
            f"unknown record name(s) {', '.join(unknown)}; choose from {', '.join(RECORD_NAMES)}"
        )
    return names


def register(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """Add `decode` and `dbc` to the `eqgw` command."""
    p = sub.add_parser(
        "decode",
        help="decode the equalizer messages of a CAN log to JSON lines",
        description="Decode every equalizer message in a CAN log file (any format python-can's "
        "LogReader reads: .log, .log.gz, .asc, .blf, .trc, .csv) to one JSON object per line.",
    )
    p.add_argument("file", help="CAN log file")
    p.add_argument(
        "--sa", type=parse_sas, default=[0x1E], help="equalizer source addresses (default 30)"
    )
    p.add_argument("--only", type=_parse_only, default=None, help="record names to print")
    p.add_argument(
        "--request-byte-order",
        choices=("lsb", "msb"),
        default="lsb",
        help="byte order of the PGN in Request frames (J1939-21: lsb)",
    )
    p.set_defaults(func=run_decode)
    d = sub.add_parser("dbc", help="print the equalizer DBC file")
    d.set_defaults(func=run_dbc)


def run_dbc(args: argparse.Namespace) -> int:
    from eqgw.protocol.dbc import dbc_text

    sys.stdout.write(dbc_text())
    return 0


_BAD_LINES_SHOWN = 10
# Exit code of `decode` and `replay` on a log cut short whose frames before the cut were read
# (a truncated MF4).
SALVAGED_EXIT = 3


def _error(message: str) -> int:
    print(f"eqgw decode: {message}", file=sys.stderr)
    return 2


def _bad_lines_summary(count: int, bad: list[tuple[int, str]]) -> str:
    shown = "; ".join(f"line {n}: {reason}" for n, reason in bad[:_BAD_LINES_SHOWN])
    more = f"; {count - _BAD_LINES_SHOWN} more" if count > _BAD_LINES_SHOWN else ""
    return f"malformed lines: {count} ({shown}{more})"


def run_decode(args: argparse.Namespace) -> int:
    import orjson

    from eqgw.bus.candump import CandumpReader, is_candump_path
    from eqgw.bus.errors import LogFileError
    from eqgw.bus.replay import blf_truncation, open_log_reader, salvage_notice
    from eqgw.describe import describe
    from eqgw.protocol.decode import FrameDecoder, lookalike_summary

    path: str = args.file
    if not os.path.exists(path):
        return _error(f"{path}: no such file")
    if os.path.isdir(path):
        return _error(f"{path}: is a directory")
    if not os.access(path, os.R_OK):
        return _error(f"{path}: permission denied")
    decoder = FrameDecoder(args.sa, request_byte_order=args.request_byte_order, only=args.only)
    out = sys.stdout
    out.flush()
    # orjson: the JSON encoding is most of the cost of a decoded record with the stdlib encoder.
    dumps = orjson.dumps
    newline = orjson.OPT_APPEND_NEWLINE
    write = out.buffer.write
    failure: str | None = None
    candump: CandumpReader | None = None
    reader: LogReader | None = None
    try:
        if is_candump_path(path):
            # Our own candump reader: the same frames as python-can's, but a bad line is
            # counted and skipped instead of ending the file, and it reads 3x faster.
            candump = CandumpReader(path)
            records: Iterator[Record] = decoder.decode_frames(candump)
        else:
            reader = open_log_reader(path)
            records = (rec for msg in reader for rec in decoder.decode_message(msg))
    except LogFileError as exc:
        return _error(str(exc))
    except Exception as exc:
        return _error(f"{path}: cannot read: {describe(exc)}")
    try:
        for rec in records:
            write(dumps(rec.to_dict(), option=newline))
    except BrokenPipeError:
        # `eqgw decode big.log | head` is normal use, not an error.
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, out.fileno())
        return 0
    except Exception as exc:
        failure = f"{path}: unreadable after {decoder.stats.frames} frames: {describe(exc)}"
    finally:
        if reader is not None:
            reader.stop()
    decoder.finish()
    out.flush()
    s = decoder.stats
    malformed = s.malformed
    frames = s.frames
    if candump is not None:
        if candump.untimed_plain and not candump.frames:
            return _error(
                f"{path}: plain candump output without timestamps; record with "
                "`candump -L` (or `candump -ta`) to keep the frames' times"
            )
        if candump.bad_lines and not candump.frames and failure is None:
            return _error(f"{path}: not a candump log (no line of {candump.bad_lines} is a frame)")
        malformed += candump.bad_lines
        frames += candump.bad_lines
    elif reader is not None and failure is None:
        failure = blf_truncation(reader, path)
    salvaged = salvage_notice(reader) if failure is None else None
    print(
        f"frames read: {frames}, records: {s.records}, ignored (other nodes): {s.ignored}, "
        f"malformed: {malformed}, multi-packet transfers: {s.transfers_completed} complete, "
        f"{s.transfers_incomplete} incomplete, {s.transfers_broken} broken"
        + (
            f", DM1s between other nodes by RTS/CTS: {s.other_dm1_transfers}"
            if s.other_dm1_transfers
            else ""
        ),
        file=sys.stderr,
    )
    if s.lookalike:
        print(lookalike_summary(s.lookalike, args.sa), file=sys.stderr)
    if candump is not None and candump.bad_lines:
        print(_bad_lines_summary(candump.bad_lines, candump.bad), file=sys.stderr)
    if failure:
        return _error(failure)
    if salvaged is not None:
        # What was before the cut is decoded; 3 says so to a script (2: nothing recovered).
        _error(f"{path}: {salvaged}")
        return SALVAGED_EXIT if frames else 2
    return 0
