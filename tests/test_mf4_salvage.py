"""A truncated MF4 keeps what was read: every whole record before the cut comes back bit for
bit (python-can's MF4Writer files, and CANedge-style files with their directory first, an
unsorted data group and DZ blocks); `decode` and `replay` say it in one line and exit 3."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import can
import pytest

from eqgw.bus import mf4
from eqgw.bus.errors import LogFileError
from eqgw.bus.mf4_salvage import Mf4Salvage, find_cut
from eqgw.bus.replay import LogReplaySource, open_log_reader, salvage_notice
from eqgw.cli import main
from tests.fixtures import mixed_log
from tests.mf4_helpers import canedge_style, write_python_can_mf4

# Found, not imported: an import here would load asammdf (numpy, pandas, sympy) into every test
# process at collection (tests/conftest.py).
if importlib.util.find_spec("asammdf") is None:
    pytest.skip("asammdf (the mf4 extra) is not installed", allow_module_level=True)


@pytest.fixture(autouse=True)
def _mf4_loaded() -> None:
    """python-can's MF4 reader and writer with asammdf: the tests use them directly, and
    eqgw's import had them load without it until an MF4 log is asked for (eqgw.bus.mf4)."""
    assert mf4.load()


# python-can's MF4Writer file: ID, HD (64..168), HD comment (168..248), then the first DT
# block's header (248..272) and its 84-byte records.
DATA_START = 272
RECORD = 84


def _frames() -> list[can.Message]:
    frames = list(can.LogReader(str(mixed_log.LOG)))
    for msg in frames:
        msg.channel = {"can0": 0, "can1": 1}[msg.channel]
    return frames


def _key(m: can.Message) -> tuple[object, ...]:
    return (
        m.timestamp.hex(),  # bit for bit
        m.arbitration_id,
        m.is_extended_id,
        m.dlc,
        bytes(m.data),
        m.is_remote_frame,
        m.channel,
        m.is_rx,
    )


def _read(path: Path) -> tuple[list[can.Message], str | None]:
    reader = open_log_reader(path)
    with reader:
        frames = list(reader)
    return frames, salvage_notice(reader)


@pytest.fixture(scope="module")
def written() -> list[can.Message]:
    return _frames()


@pytest.fixture(scope="module")
def plain_mf4(tmp_path_factory: pytest.TempPathFactory, written: list[can.Message]) -> Path:
    path = tmp_path_factory.mktemp("mf4") / "whole.mf4"
    write_python_can_mf4(path, written, level=0)
    return path


def _cut(src: Path, dst: Path, at: int) -> Path:
    dst.write_bytes(src.read_bytes()[:at])
    return dst


@pytest.mark.parametrize(
    ("at", "n", "partial"),
    [
        (DATA_START + 1000 * RECORD, 1000, 0),  # inside the data block, at a record's end
        (DATA_START + 1000 * RECORD + 40, 1000, 1),  # inside a record
        (DATA_START + RECORD - 1, 0, 1),  # inside the first record
        (DATA_START + 3893 * RECORD, 3893, 0),  # after the data: the directory lost whole
    ],
)
def test_python_can_mf4_cut_keeps_the_frames_before_the_cut(
    tmp_path: Path, plain_mf4: Path, written: list[can.Message], at: int, n: int, partial: int
) -> None:
    assert len(written) == 3893
    cut = _cut(plain_mf4, tmp_path / "cut.mf4", at)
    assert find_cut(cut) is not None
    frames, notice = _read(cut)
    assert [_key(m) for m in frames] == [_key(m) for m in written[:n]]
    assert notice is not None and notice.startswith(f"truncated MF4: recovered {n} frames ")
    assert ("1 partial record dropped" in notice) == bool(partial)


def test_a_cut_in_the_directory_loses_no_frame(
    tmp_path: Path, plain_mf4: Path, written: list[can.Message]
) -> None:
    size = plain_mf4.stat().st_size
    frames, notice = _read(_cut(plain_mf4, tmp_path / "cut.mf4", size - 10))
    assert [_key(m) for m in frames] == [_key(m) for m in written]
    assert notice == (
        "truncated MF4: recovered 3893 frames up to 2025-11-21 04:41:59.900 UTC, the rest of "
        "the file is cut off"
    )


def test_a_cut_just_after_the_header_recovers_nothing_in_one_line(
    tmp_path: Path, plain_mf4: Path
) -> None:
    cut = _cut(plain_mf4, tmp_path / "cut.mf4", 248)
    with pytest.raises(LogFileError) as info:
        open_log_reader(cut)
    assert str(info.value) == (
        f"{cut}: truncated MF4: nothing to recover: the channel directory is cut off, and no "
        "data block is before the cut"
    )


def test_a_whole_file_is_read_by_python_can_as_before(plain_mf4: Path) -> None:
    assert find_cut(plain_mf4) is None
    reader = open_log_reader(plain_mf4)
    reader.stop()
    assert not isinstance(reader, Mf4Salvage)


def test_deflate_blocks_cut_short_give_their_records_up_to_the_cut(
    tmp_path: Path, written: list[can.Message]
) -> None:
    whole = tmp_path / "deflate.mf4"
    write_python_can_mf4(whole, written, level=1)
    frames, notice = _read(_cut(whole, tmp_path / "cut.mf4", whole.stat().st_size // 2))
    assert 0 < len(frames) < len(written)
    assert [_key(m) for m in frames] == [_key(m) for m in written[: len(frames)]]
    assert notice is not None and notice.startswith(f"truncated MF4: recovered {len(frames)} ")


def test_a_transposed_block_cut_short_holds_no_whole_record_and_says_so(
    tmp_path: Path, written: list[can.Message]
) -> None:
    whole = tmp_path / "transposed.mf4"
    write_python_can_mf4(whole, written, level=2)  # python-can's default
    frames, notice = _read(_cut(whole, tmp_path / "cut.mf4", whole.stat().st_size // 2))
    assert frames == []
    assert notice == (
        "truncated MF4: recovered 0 frames (none before the cut), the rest of the file is cut "
        "off (3893 records of a compressed block cut short lost)"
    )


@pytest.fixture(scope="module")
def canedge_frames() -> list[can.Message]:
    frames = _frames()
    # A remote frame: a second channel group, its records interleaved with the data frames.
    at = frames[5].timestamp
    frames.insert(6, can.Message(timestamp=at, arbitration_id=0x18EA1E00, is_remote_frame=True))
    frames[6].dlc, frames[6].channel = 3, 0
    return frames


@pytest.fixture(scope="module")
def canedge_mf4(
    tmp_path_factory: pytest.TempPathFactory, canedge_frames: list[can.Message]
) -> Path:
    folder = tmp_path_factory.mktemp("canedge")
    source = folder / "source.mf4"
    write_python_can_mf4(source, canedge_frames, level=0)
    path = folder / "00000001.MF4"
    canedge_style(source, path, block_bytes=4096, zipped=True)
    # asammdf reads the re-laid file as the frames written: the layout is a valid MF4.
    with can.LogReader(str(path)) as reader:
        assert [_key(m) for m in reader] == [_key(m) for m in canedge_frames]
    return path


@pytest.mark.parametrize("fraction", [0.2, 0.3, 0.5, 0.77, 0.999])
def test_canedge_style_file_cut_keeps_the_records_of_its_dz_blocks(
    tmp_path: Path, canedge_mf4: Path, canedge_frames: list[can.Message], fraction: float
) -> None:
    data = canedge_mf4.read_bytes()
    cut = tmp_path / "cut.MF4"
    cut.write_bytes(data[: int(len(data) * fraction)])
    frames, notice = _read(cut)
    assert [_key(m) for m in frames] == [_key(m) for m in canedge_frames[: len(frames)]]
    assert notice is not None and notice.startswith(f"truncated MF4: recovered {len(frames)} ")
    assert frames
    if fraction > 0.99:  # the last DZ block cut short: its records before the cut kept
        assert len(frames) > len(canedge_frames) - 4096 // 85
    assert any(m.is_remote_frame for m in frames) == (len(frames) > 6)


def test_canedge_style_file_cut_in_its_directory_is_one_error_line(
    tmp_path: Path, canedge_mf4: Path
) -> None:
    cut = _cut(canedge_mf4, tmp_path / "cut.MF4", 2000)
    with pytest.raises(
        LogFileError,
        match=r"truncated MF4: nothing to recover: a channel .* is cut off, and no data block",
    ):
        open_log_reader(cut)


def test_canedge_style_unfinalized_file_is_read_to_its_last_whole_record(
    tmp_path: Path, canedge_frames: list[can.Message]
) -> None:
    """A logger still recording leaves its DT block's length unwritten; asammdf finalizes
    such a file and reads it up to the end of the file (its last whole record)."""
    source = tmp_path / "source.mf4"
    write_python_can_mf4(source, canedge_frames, level=0)
    path = tmp_path / "unfinalized.MF4"
    canedge_style(source, path, zipped=False, unfinalized=True)
    data = path.read_bytes()
    cut = tmp_path / "cut.MF4"
    cut.write_bytes(data[: len(data) * 2 // 3])
    frames, notice = _read(cut)
    assert 0 < len(frames) < len(canedge_frames) and notice is None
    assert [_key(m) for m in frames] == [_key(m) for m in canedge_frames[: len(frames)]]


def test_any_cut_is_the_frames_before_it_or_one_error_line(
    tmp_path: Path, written: list[can.Message], canedge_frames: list[can.Message]
) -> None:
    """Cut at every 17th byte of small files of both layouts: never a traceback, never a
    frame that was not written, and the frames are always the first ones written."""
    cases = []
    plain = tmp_path / "plain.mf4"
    write_python_can_mf4(plain, written[:60], level=0)
    cases.append((plain, written[:60]))
    source = tmp_path / "source.mf4"
    write_python_can_mf4(source, canedge_frames[:60], level=0)
    edge = tmp_path / "edge.mf4"
    canedge_style(source, edge, block_bytes=700, zipped=True)
    cases.append((edge, canedge_frames[:60]))
    cut = tmp_path / "cut.mf4"
    for path, frames in cases:
        data = path.read_bytes()
        for at in range(0, len(data), 17):
            cut.write_bytes(data[:at])
            try:
                got, _ = _read(cut)
            except LogFileError as exc:
                assert "\n" not in str(exc)
                continue
            assert [_key(m) for m in got] == [_key(m) for m in frames[: len(got)]], at


def test_decode_and_replay_say_it_in_one_line_and_exit_3(
    tmp_path: Path, plain_mf4: Path, capfd: pytest.CaptureFixture[str]
) -> None:
    assert main(["decode", str(plain_mf4), "--sa", "30,31"]) == 0
    whole = [json.loads(line) for line in capfd.readouterr().out.splitlines()]
    cut = _cut(plain_mf4, tmp_path / "cut.mf4", DATA_START + 2000 * RECORD + 17)
    rc = main(["decode", str(cut), "--sa", "30,31"])
    out, err = capfd.readouterr()
    records = [json.loads(line) for line in out.splitlines()]
    assert rc == 3
    assert 0 < len(records) < len(whole) and records == whole[: len(records)]
    line = (
        f"{cut}: truncated MF4: recovered 2000 frames up to 2025-11-21 04:41:00.700 UTC, the "
        "rest of the file is cut off (1 partial record dropped)"
    )
    assert err.splitlines()[0].startswith("frames read: 2000, ")
    assert err.splitlines()[-1] == f"eqgw decode: {line}"
    assert "Traceback" not in err and "asammdf" not in err
    db = f"sqlite:///{tmp_path / 'r.db'}"
    rc_replay = main(["replay", str(cut), "--vehicle", "BUS-9", "--db", db, "-q", "--json"])
    out, err = capfd.readouterr()
    assert rc_replay == rc
    summary = json.loads(out)
    assert summary["frames"] == 2000 and summary["truncated"] == line.split(": ", 1)[1]
    assert err == f"eqgw replay: {line}\n"


def test_decode_and_replay_exit_2_when_nothing_was_before_the_cut(
    tmp_path: Path, plain_mf4: Path, capfd: pytest.CaptureFixture[str]
) -> None:
    cut = _cut(plain_mf4, tmp_path / "cut.mf4", DATA_START + 50)
    assert main(["decode", str(cut)]) == 2
    err = capfd.readouterr().err
    assert err.splitlines()[-1] == (
        f"eqgw decode: {cut}: truncated MF4: recovered 0 frames (none before the cut), the "
        "rest of the file is cut off (1 partial record dropped)"
    )
    db = f"sqlite:///{tmp_path / 'r.db'}"
    assert main(["replay", str(cut), "--vehicle", "BUS-9", "--db", db, "-q"]) == 2
    assert "Traceback" not in capfd.readouterr().err


def test_live_replay_reads_the_frames_before_the_cut(
    tmp_path: Path, plain_mf4: Path, written: list[can.Message], caplog: pytest.LogCaptureFixture
) -> None:
    cut = _cut(plain_mf4, tmp_path / "cut.mf4", DATA_START + 100 * RECORD)
    frames = list(LogReplaySource(cut))
    assert [(m.arbitration_id, bytes(m.data)) for m in frames] == [
        (m.arbitration_id, bytes(m.data)) for m in written[:100]
    ]
    assert "truncated MF4: recovered 100 frames" in caplog.text
