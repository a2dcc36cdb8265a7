"""Our candump reader reads exactly what python-can's CanutilsLogReader reads, frame by frame,
on every fixture log and on the odd cases (remote, error, FD, standard ids, directions)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import can
import pytest

from eqgw.bus.candump import CandumpReader
from tests.fixtures import mixed_log

# Lines python-can reads; each one an odd case of the candump -L format.
ODD_LINES = [
    "(1763700000.000100) can0 18FFD61E#D809B013BA7CC87D R",  # extended, received
    "(1763700000.000200) can0 18FFD61E#D809B013BA7CC87D T",  # transmitted
    "(1763700000.000300) can1 18FFD61E#D809B013",  # no direction, short
    "(1763700000.000400) vcan0 123#8D00100100820100",  # standard id
    "(1763700000.000500) can0 7FF#",  # standard id, no data
    "(1763700000.000600) can0 18FECA1E#",  # extended, no data
    "(1763700000.000700) can0 123#R",  # remote, no length
    "(1763700000.000800) can0 18EA1ED8#R3",  # remote with a length
    "(1763700000.000900) can0 18EA1ED8#r",  # remote, lower case
    "(1763700000.001000) can0 20000080#0000000000000000",  # error frame (bus error)
    "(1763700000.001100) can0 20000004#0000000000000000",  # error class without bus error
    "(1763700000.001200) can0 18FFD61E##1" + "11" * 64,  # FD, bit rate switch, 64 bytes
    "(1763700000.001300) can0 18FFD61E##2" + "22" * 12,  # FD, error state indicator
    "(1763700000.001400) can0 123##0AABB",  # FD, no flags, standard id
    "(1763700000.001500) can0 18FFD61E#" + "AB" * 32,  # more than 8 bytes, not flagged FD
    "(1763700000.001600) 3 18FFD61E#D809 R",  # numeric channel
    "(1763700000.001700) 07 18FFD61E#D809 R",  # numeric channel with a leading zero
    "(0.0) can0 0#00",  # id 0, timestamp 0
    "(1763700000.001800) can0 0000001E#00",  # 8-digit id that fits 11 bits
    "(1763700000.001900) can0 18ffd61e#d809b013ba7cc87d R",  # lower-case hex
    "(1763700000.002000) can0 1FFFFFFF#FF",  # largest id
    "(-1.5) can0 18FFD61E#D809",  # negative timestamp
    "(1e3) can0 18FFD61E#D809",  # exponent timestamp
    "",  # blank lines are skipped by both
    "   (1763700000.002100)   can0   18FFD61E#D809   R   ",  # extra spaces
]


def _key(m: can.Message) -> tuple[Any, ...]:
    return (
        m.timestamp,
        m.arbitration_id,
        m.is_extended_id,
        m.is_remote_frame,
        m.is_error_frame,
        m.is_fd,
        m.bitrate_switch,
        m.error_state_indicator,
        m.dlc,
        bytes(m.data),
        m.channel,
        m.is_rx,
    )


def _tuple_of(m: can.Message) -> tuple[Any, ...]:
    """The decoder's view of a python-can message (what `FrameDecoder.decode_message` reads)."""
    channel = None if m.channel is None else str(m.channel)
    return (
        m.timestamp,
        channel,
        m.arbitration_id,
        bytes(m.data),
        m.is_extended_id,
        m.is_remote_frame,
        m.is_error_frame,
    )


def _sim_log(tmp_path: Path) -> Path:
    """A log the simulator records with background traffic (its own writer: python-can's)."""
    from eqgw.sim.clock import ManualClock
    from eqgw.sim.fleet import SimulatedFleet

    path = tmp_path / "sim.log"
    fleet = SimulatedFleet(2, seed=3, clock=ManualClock(), background_traffic=True)
    bus = can.Bus(interface="virtual", channel=fleet.channels["SIM-001"])
    try:
        fleet.open()
        fleet.advance(20.0)
        with can.CanutilsLogWriter(str(path)) as writer:
            while (msg := bus.recv(0)) is not None:
                writer.on_message_received(msg)
    finally:
        bus.shutdown()
        fleet.close()
    return path


def _logs(tmp_path: Path) -> list[Path]:
    odd = tmp_path / "odd.log"
    odd.write_text("\n".join(ODD_LINES) + "\n")
    written = tmp_path / "written.log"
    # python-can's own writer for every odd message the reader produced.
    with can.CanutilsLogWriter(str(written)) as writer:
        for msg in can.LogReader(str(odd)):
            if not msg.is_error_frame:  # its writer cannot write a channel-less error frame
                writer.on_message_received(msg)
    return [mixed_log.LOG, odd, written, _sim_log(tmp_path)]


def test_frame_by_frame_identical_to_python_can(tmp_path: Path) -> None:
    for path in _logs(tmp_path):
        theirs = list(can.LogReader(str(path)))
        assert len(theirs) > 10, path
        ours = CandumpReader(path)
        mine = list(ours.messages())
        assert ours.bad_lines == 0, (path, ours.bad)
        assert len(mine) == len(theirs), path
        for i, (a, b) in enumerate(zip(theirs, mine, strict=True)):
            assert _key(a) == _key(b), (path.name, i)
        # The tuples the decoder's fast path reads say the same as python-can's messages.
        fast = list(CandumpReader(path))
        assert [_tuple_of(m) for m in theirs] == fast, path.name


def test_odd_cases_cover_what_they_claim(tmp_path: Path) -> None:
    odd = tmp_path / "odd.log"
    odd.write_text("\n".join(ODD_LINES) + "\n")
    msgs = list(CandumpReader(odd).messages())
    assert any(m.is_remote_frame for m in msgs)
    assert any(m.is_error_frame for m in msgs)
    assert any(m.is_fd and m.bitrate_switch for m in msgs)
    assert any(m.is_fd and m.error_state_indicator for m in msgs)
    assert any(not m.is_extended_id for m in msgs) and any(m.is_extended_id for m in msgs)
    assert any(not m.is_rx for m in msgs)
    assert any(m.channel == 7 for m in msgs)


@pytest.mark.parametrize(
    ("line", "reason"),
    [
        ("(1.0) can0 18FFD61E#ABC", "odd number of hex digits"),
        ("(nan) can0 18FFD61E#D809", "not a finite number"),
        ("(inf) can0 18FFD61E#D809", "not a finite number"),
        ("(x) can0 18FFD61E#D809", "not a number"),
        ("1.0 can0 18FFD61E#D809", "no (timestamp)"),
        ("(1.0) can0 18FFD61G#D809", "not 1-8 hex digits"),
        ("(1.0) can0 18FFD61E#ZZ", "not hex"),
        ("(1.0) can0 18FFD61E#D809 R extra", "not a candump line"),
        ("hello world", "not a candump line"),
        ("  can0  18FFD61E   [8]  D8 09 B0 13 BA 7C C8 7D", "without a timestamp"),
        ("(1.0)  can0  18FFD61E   [3]  D8 09", "[3] but 2 data bytes"),
    ],
)
def test_bad_lines_are_counted_with_their_numbers_and_reading_goes_on(
    tmp_path: Path, line: str, reason: str
) -> None:
    path = tmp_path / "bad.log"
    path.write_text(f"(1.0) can0 18FFD61E#D809\n{line}\n(2.0) can0 18FFD61E#D80A\n")
    reader = CandumpReader(path)
    frames = list(reader)
    assert [f[0] for f in frames] == [1.0, 2.0]
    assert reader.bad_lines == 1 and reader.bad[0][0] == 2 and reason in reader.bad[0][1]
    again = CandumpReader(path)
    assert [m.timestamp for m in again.messages()] == [1.0, 2.0] and again.bad == reader.bad


def test_plain_candump_with_absolute_times_reads_as_candump_l(tmp_path: Path) -> None:
    plain = tmp_path / "plain.txt"
    plain.write_text(
        " (1763700000.100000)  can0  18FFD61E   [8]  D8 09 B0 13 BA 7C C8 7D\n"
        " (1763700000.200000)  can0  123   [2]  0A 0B\n"
        " (1763700000.300000)  can0  18EA1ED8   [3]  remote request\n"
        " (1763700000.400000)  can0  18FFD41E   [2]  41 55   'AU'\n"
    )
    ref = tmp_path / "ref.log"
    ref.write_text(
        "(1763700000.100000) can0 18FFD61E#D809B013BA7CC87D\n"
        "(1763700000.200000) can0 123#0A0B\n"
        "(1763700000.300000) can0 18EA1ED8#R3\n"
        "(1763700000.400000) can0 18FFD41E#4155\n"
    )
    assert [_key(m) for m in CandumpReader(plain).messages()] == [
        _key(m) for m in can.LogReader(str(ref))
    ]
