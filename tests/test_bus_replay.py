"""Log files as a frame source: every format python-can writes, and the broken ones."""

from __future__ import annotations

import asyncio
import gzip
from pathlib import Path

import can
import pytest

from eqgw.bus.errors import BusError, LogFileError
from eqgw.bus.replay import LogReplaySource

FORMATS = [".log", ".log.gz", ".asc", ".asc.gz", ".blf", ".trc", ".csv"]


def recorded() -> list[can.Message]:
    return [
        can.Message(
            timestamp=1_700_000_000.0 + i * 0.0125,
            arbitration_id=0x18FEF11E if i % 2 else 0x0CF00400,
            data=bytes([i, 0xFF, 0x00, i]) + bytes(i % 5),
            channel="can0",
        )
        for i in range(40)
    ]


def write_log(path: Path, messages: list[can.Message]) -> Path:
    with can.Logger(path) as logger:
        for msg in messages:
            logger(msg)
    return path


@pytest.mark.parametrize("suffix", FORMATS)
def test_every_format_replays_frames_timestamps_and_channels(tmp_path: Path, suffix: str) -> None:
    original = recorded()
    path = write_log(tmp_path / f"trip{suffix}", original)
    # What becomes of "can0" depends on the format: a name (.log), 0 (.asc, .blf), 1 (.trc),
    # nothing (.csv).
    source = LogReplaySource(
        path,
        channel_map={"can0": "BUS-101/can0", "0": "BUS-101/can0", "1": "BUS-101/can0"},
        default_channel="BUS-101/can0",
    )
    frames = list(source)
    assert source.frames == len(original)
    assert [m.arbitration_id for m in frames] == [m.arbitration_id for m in original]
    assert [bytes(m.data) for m in frames] == [bytes(m.data) for m in original]
    assert all(m.is_extended_id for m in frames)
    assert all(m.channel == "BUS-101/can0" for m in frames)
    # Absolute bus time survives (ASC included): decoders and fault tracking key on it.
    for got, want in zip(frames, original, strict=True):
        assert got.timestamp == pytest.approx(want.timestamp, abs=1e-3)


def test_unmapped_channels_keep_their_name(tmp_path: Path) -> None:
    messages = recorded()[:4]
    messages[1].channel = "can1"
    path = write_log(tmp_path / "two.log", messages)
    frames = list(LogReplaySource(path, channel_map={"can0": "BUS-101/can0"}))
    assert [m.channel for m in frames] == ["BUS-101/can0", "can1", "BUS-101/can0", "BUS-101/can0"]


async def test_async_iteration_yields_to_the_loop(tmp_path: Path) -> None:
    path = write_log(tmp_path / "trip.blf", recorded())
    ticks = 0

    async def tick() -> None:
        nonlocal ticks
        while True:
            ticks += 1
            await asyncio.sleep(0)

    ticker = asyncio.create_task(tick())
    try:
        frames = [m async for m in LogReplaySource(path, yield_every=5)]
    finally:
        ticker.cancel()
        with pytest.raises(asyncio.CancelledError):
            await ticker
    assert len(frames) == 40
    assert ticks >= 40 // 5 - 1


@pytest.mark.parametrize(
    ("name", "content", "reason"),
    [
        ("missing.log", None, "no such log file"),
        ("notes.txt", b"hello", "unknown log format .txt"),
        ("noext", b"hello", "unknown log format (none)"),
        ("broken.blf", b"garbage" * 10, "cannot read"),
        ("broken.log", b"(1.0) can0 ZZZ#11\n", "unreadable after frame 0"),
        ("broken.log.gz", b"not gzip at all", "unreadable after frame 0"),
        ("half.log", b"(1.0) can0 123#11\n(1.1) can0 ZZZ#11\n", "unreadable after frame 1"),
    ],
)
def test_broken_files_raise_one_line_bus_errors(
    tmp_path: Path, name: str, content: bytes | None, reason: str
) -> None:
    path = tmp_path / name
    if content is not None:
        path.write_bytes(content)
    with pytest.raises(LogFileError) as caught:
        list(LogReplaySource(path))
    message = str(caught.value)
    assert isinstance(caught.value, BusError)
    assert reason in message
    assert str(path) in message
    assert "\n" not in message


def test_gzip_of_a_text_log_is_read(tmp_path: Path) -> None:
    path = tmp_path / "candump.log.gz"
    with gzip.open(path, "wt") as f:
        f.write("(1700000000.500000) can0 18FEF11E#0102\n")
    (msg,) = LogReplaySource(path)
    assert msg.arbitration_id == 0x18FEF11E and msg.data == b"\x01\x02"
    assert msg.timestamp == 1_700_000_000.5
    assert msg.channel == "can0"
