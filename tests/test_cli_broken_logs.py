"""`eqgw decode` on broken logs: bad lines counted with their numbers while decoding goes on,
plain candump output read or named, truncation said with a non-zero exit."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import can
import pytest

from eqgw.bus import mf4
from eqgw.cli import main
from tests.fixtures import mixed_log

VOLTAGES = "(1763700000.000000) can0 18FFD61E#D809B013BA7CC87D R"


def _run(capsys: pytest.CaptureFixture[str], *args: str) -> tuple[int, list[dict[str, Any]], str]:
    rc = main(["decode", *args])
    out, err = capsys.readouterr()
    return rc, [json.loads(line) for line in out.splitlines()], err


def _expected() -> list[dict[str, Any]]:
    return [json.loads(line) for line in mixed_log.EXPECTED.read_text().splitlines()]


def test_junk_lines_are_malformed_with_line_numbers_and_decoding_goes_on(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    lines = mixed_log.LOG.read_text().splitlines()
    lines.insert(100, "garbage here with too many values to unpack")
    lines.insert(2000, "(1763700000.5) can0 18FFD61E#ABC R")  # odd hex: not AB 0C
    lines.insert(3000, "(nan) can0 18FFD61E#D809B013BA7CC87D R")  # NaN time: not "ts":null
    path = tmp_path / "broken.log"
    path.write_text("\n".join(lines) + "\n")
    rc, records, err = _run(capsys, str(path), "--sa", "30,31")
    assert rc == 0
    assert records == _expected()  # every record of the intact lines, nothing else
    summary, lookalike, bad = err.strip().splitlines()
    assert lookalike.startswith("equalizer-like frames (PGN 0xFFD4-0xFFD9) from addresses not")
    assert summary == (
        "frames read: 3896, records: 640, ignored (other nodes): 3216, malformed: 7, "
        "multi-packet transfers: 11 complete, 2 incomplete, 3 broken"
    )
    assert bad.startswith("malformed lines: 3 (line 101: not a candump line; line 2001: ")
    assert "odd number of hex digits" in bad and "line 3001: timestamp 'nan'" in bad
    assert "unpack" not in err and "Traceback" not in err


def test_64_byte_line_is_not_voltages(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / "fd.log"
    path.write_text(
        VOLTAGES + "\n"
        "(1763700001.0) can0 18FFD61E#" + "D8" * 32 + " R\n"
        "(1763700002.0) can0 18FFD61E##1" + "4F" * 64 + " R\n"
    )
    rc, records, err = _run(capsys, str(path))
    assert rc == 0 and [r["ts"] for r in records] == [1763700000.0]
    assert "frames read: 3, records: 1, ignored (other nodes): 0, malformed: 2" in err


def test_plain_candump_without_timestamps_is_named(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "plain.log"
    path.write_text(
        "  can0  18FFD61E   [8]  D8 09 B0 13 BA 7C C8 7D\n"
        "  can0  0CF00400   [8]  F0 7D 7D E9 18 00 F0 7D\n"
    )
    rc, records, err = _run(capsys, str(path))
    assert rc == 2 and records == []
    assert err.count("\n") == 1
    assert "plain candump output without timestamps" in err and "candump -L" in err


def test_plain_candump_with_absolute_times_decodes(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    plain = tmp_path / "plain.txt"
    with plain.open("w") as out:
        for m in can.LogReader(str(mixed_log.LOG)):
            data = " ".join(f"{b:02X}" for b in m.data)
            cid = f"{m.arbitration_id:08X}" if m.is_extended_id else f"{m.arbitration_id:03X}"
            out.write(f" ({m.timestamp:.6f})  {m.channel}  {cid}   [{len(m.data)}]  {data}\n")
    rc, records, err = _run(capsys, str(plain), "--sa", "30,31")
    assert rc == 0 and "malformed lines" not in err
    assert records == _expected()


def test_a_file_with_no_candump_line_is_an_error(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "notes.log"
    path.write_text("this is\nnot a log\n")
    rc, _, err = _run(capsys, str(path))
    assert rc == 2 and err == f"eqgw decode: {path}: not a candump log (no line of 2 is a frame)\n"


def _write_fixture(path: Path) -> int:
    """The mixed-bus fixture written in the format of `path`'s suffix (numbered channels)."""
    frames = list(can.LogReader(str(mixed_log.LOG)))
    mf4.load()  # for an .mf4 path: python-can's MF4 writer with asammdf (eqgw.bus.mf4)
    with can.Logger(str(path)) as writer:
        for msg in frames:
            msg.channel = {"can0": 0, "can1": 1}[msg.channel]
            writer.on_message_received(msg)
    return len(frames)


def test_truncated_blf_is_said_with_a_non_zero_exit(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    whole = tmp_path / "whole.blf"
    _write_fixture(whole)
    rc, full, err = _run(capsys, str(whole), "--sa", "30,31")
    assert rc == 0 and len(full) == 640
    cut = tmp_path / "cut.blf"
    data = whole.read_bytes()
    cut.write_bytes(data[: len(data) // 2])
    rc, records, err = _run(capsys, str(cut), "--sa", "30,31")
    assert rc == 2
    assert 0 < len(records) < len(full) and records == full[: len(records)]
    last = err.strip().splitlines()[-1]
    assert last == (
        f"eqgw decode: {cut}: truncated: the BLF header says {len(data)} bytes, "
        f"the file has {len(data) // 2}"
    )


def test_truncated_gzip_log_is_said_with_a_non_zero_exit(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    import gzip

    packed = gzip.compress(mixed_log.LOG.read_bytes())
    cut = tmp_path / "cut.log.gz"
    cut.write_bytes(packed[: len(packed) // 2])
    rc, records, err = _run(capsys, str(cut), "--sa", "30,31")
    assert rc == 2 and 0 < len(records) < 640
    assert records == _expected()[: len(records)]
    assert err.strip().splitlines()[-1].startswith(f"eqgw decode: {cut}: unreadable after ")
    assert "EOFError" in err


def test_a_huge_line_is_skipped_without_holding_it(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A corrupt log with one line of 16 MB: it is a bad line (numbered), the frames around it
    decode, and reading never holds the line (traced peak far below its size)."""
    import tracemalloc

    path = tmp_path / "huge.log"
    with path.open("w") as fh:
        fh.write(VOLTAGES + "\n")
        fh.write("A" * (16 << 20) + "\n")
        fh.write(VOLTAGES.replace("000000)", "100000)") + "\n")
    tracemalloc.start()
    try:
        rc, records, err = _run(capsys, str(path))
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert rc == 0 and len(records) == 2
    assert "malformed lines: 1 (line 2: line longer than 4096 characters)" in err
    assert peak < 2 << 20, peak


def test_a_truncated_mf4_is_one_line_in_decode_and_replay_alike(
    tmp_path: Path, capfd: pytest.CaptureFixture[str]
) -> None:
    """An MF4 cut short (a power cut): no destructor traceback, one line, and the same exit
    from `decode` and `replay`; the whole file decodes. python-can's default MF4 is one
    transposed deflate block: cut in half, no record of it is whole (2: nothing recovered;
    tests/test_mf4_salvage.py has the cuts that keep frames, exit 3)."""
    pytest.importorskip("asammdf")
    whole = tmp_path / "whole.mf4"
    _write_fixture(whole)
    rc = main(["decode", str(whole), "--sa", "30,31"])
    assert rc == 0 and len(capfd.readouterr().out.splitlines()) == 640
    cut = tmp_path / "cut.mf4"
    data = whole.read_bytes()
    cut.write_bytes(data[: len(data) // 2])
    rc = main(["decode", str(cut)])
    out, err = capfd.readouterr()
    line = (
        f"{cut}: truncated MF4: recovered 0 frames (none before the cut), the rest of the file "
        "is cut off (3893 records of a compressed block cut short lost)"
    )
    assert rc == 2 and out == ""
    assert err.splitlines()[-1] == f"eqgw decode: {line}"
    assert "Traceback" not in err and "Exception ignored" not in err
    db = f"sqlite:///{tmp_path / 'r.db'}"
    rc_replay = main(["replay", str(cut), "--vehicle", "BUS-9", "--db", db, "-q"])
    out, err = capfd.readouterr()
    assert rc_replay == rc
    assert err == f"eqgw replay: {line}\n"
    assert "Traceback" not in err and "Exception ignored" not in err


def test_a_file_with_no_frame_exits_alike_in_decode_and_replay(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "notes.log"
    path.write_text("this is\nnot a log\n")
    rc = main(["decode", str(path)])
    db = f"sqlite:///{tmp_path / 'r.db'}"
    rc_replay = main(["replay", str(path), "--vehicle", "BUS-9", "--db", db, "-q"])
    err = capsys.readouterr().err
    assert rc == rc_replay == 2
    assert f"eqgw replay: {path}: not a candump log (no line of 2 is a frame)" in err
