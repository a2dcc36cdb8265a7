"""`eqgw decode` and `eqgw dbc` end to end on the realistic mixed log, in every log format."""

from __future__ import annotations

import gzip
import json
import shutil
import subprocess
import sys
from pathlib import Path
from typing import Any

import can
import cantools
import pytest

from eqgw.cli import main
from tests.fixtures import mixed_log

FIXTURE = mixed_log.LOG


def _expected() -> list[dict[str, Any]]:
    return [json.loads(line) for line in mixed_log.EXPECTED.read_text().splitlines()]


def _run(capsys: pytest.CaptureFixture[str], *args: str) -> tuple[int, list[dict[str, Any]], str]:
    rc = main(["decode", *args])
    out, err = capsys.readouterr()
    return rc, [json.loads(line) for line in out.splitlines()], err


def test_fixture_is_current() -> None:
    """The committed log is what the generator builds (regenerate with the module as a script)."""
    built = mixed_log.build()
    assert len(built.frames) == sum(1 for _ in can.LogReader(str(FIXTURE)))
    assert [json.loads(json.dumps(r)) for r in built.expected] == _expected()


def test_decode_mixed_log_record_by_record(capsys: pytest.CaptureFixture[str]) -> None:
    rc, records, err = _run(capsys, str(FIXTURE), "--sa", "30,31")
    assert rc == 0
    expected = _expected()
    assert len(records) == len(expected) == 640
    for got, want in zip(records, expected, strict=True):
        assert got == want
    assert err.strip() == (
        "frames read: 3893, records: 640, ignored (other nodes): 3216, malformed: 4, "
        "multi-packet transfers: 11 complete, 2 incomplete, 3 broken\n"
        "equalizer-like frames (PGN 0xFFD4-0xFFD9) from addresses not decoded: "
        "SA 64 (120 frames), SA 160 (240 frames); other vendors' devices, or equalizers: "
        "to decode them, --sa 30,31,64,160"
    )


def test_default_sa_is_30_only(capsys: pytest.CaptureFixture[str]) -> None:
    rc, records, _ = _run(capsys, str(FIXTURE))
    assert rc == 0
    want = [r for r in _expected() if r["sa"] != 31]
    assert records == want


def test_only_filters_names(capsys: pytest.CaptureFixture[str]) -> None:
    rc, records, _ = _run(capsys, str(FIXTURE), "--sa", "30,31", "--only", "voltages,dm1")
    assert rc == 0
    assert records == [r for r in _expected() if r["name"] in ("voltages", "dm1")]
    dm1 = [r for r in records if r["name"] == "dm1"]
    assert [d["code"] for d in dm1[15]["fields"]["dtcs"]] == ["IMB", "UVF"]  # a BAM one


@pytest.mark.parametrize("suffix", [".log.gz", ".asc", ".blf", ".trc", ".csv"])
def test_every_log_format_python_can_reads(
    suffix: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / f"bus{suffix}"
    frames = list(can.LogReader(str(FIXTURE)))
    if suffix == ".log.gz":
        with FIXTURE.open("rb") as src, gzip.open(path, "wb") as dst:
            shutil.copyfileobj(src, dst)
    else:
        channels = {"can0": 0, "can1": 1}
        with can.Logger(str(path)) as writer:
            for msg in frames:
                if suffix in (".asc", ".blf", ".trc"):
                    msg = can.Message(
                        timestamp=msg.timestamp,
                        arbitration_id=msg.arbitration_id,
                        is_extended_id=msg.is_extended_id,
                        data=msg.data,
                        dlc=msg.dlc,
                        channel=channels[msg.channel],
                    )
                writer.on_message_received(msg)
    rc, records, _ = _run(capsys, str(path), "--sa", "30,31")
    assert rc == 0
    expected = _expected()
    if suffix == ".csv":
        # The CSV format has no channel: both buses interleave under one key, so a unit's
        # series and BAMs can no longer be told apart. Count what is unambiguous.
        assert sum(r["name"] == "voltages" for r in records) == sum(
            r["name"] == "voltages" for r in expected
        )
        return
    assert len(records) == len(expected)
    # .asc and .trc keep time relative to the start of the log: compare offsets.
    base_got, base_want = records[0]["ts"], expected[0]["ts"]
    for got, want in zip(records, expected, strict=True):
        assert got["ts"] - base_got == pytest.approx(want["ts"] - base_want, abs=1e-4)
        assert (got["sa"], got["pgn"], got["name"], got["fields"]) == (
            want["sa"],
            want["pgn"],
            want["name"],
            want["fields"],
        )


def test_missing_file_is_one_line_and_exit_2(capsys: pytest.CaptureFixture[str]) -> None:
    rc, records, err = _run(capsys, "/nonexistent/bus.log")
    assert rc == 2 and records == []
    assert err == "eqgw decode: /nonexistent/bus.log: no such file\n"


# python-can's BLFReader leaves its file open when the header is invalid (it raises in __init__).
@pytest.mark.filterwarnings("ignore::pytest.PytestUnraisableExceptionWarning")
def test_directory_and_garbage_are_one_line_errors(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    rc, _, err = _run(capsys, str(tmp_path))
    assert rc == 2 and err.count("\n") == 1 and "is a directory" in err
    junk = tmp_path / "junk.blf"
    junk.write_bytes(b"\x00not a blf file at all" * 10)
    rc, _, err = _run(capsys, str(junk))
    assert rc == 2
    assert err.splitlines()[-1].startswith(f"eqgw decode: {junk}")
    assert "Traceback" not in err
    unknown = tmp_path / "bus.xyz"
    unknown.write_text("hello")
    rc, _, err = _run(capsys, str(unknown))
    assert rc == 2 and err.count("\n") == 1 and "Traceback" not in err


def test_bad_options_exit_2(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exc:
        main(["decode", str(FIXTURE), "--only", "volts"])
    assert exc.value.code == 2
    assert "unknown record name(s) volts" in capsys.readouterr().err


def test_console_script_and_dbc_command(tmp_path: Path) -> None:
    proc = subprocess.run(
        [sys.executable, "-m", "eqgw.cli", "dbc"], capture_output=True, text=True, check=True
    )
    dbc_file = tmp_path / "eq.dbc"
    dbc_file.write_text(proc.stdout)
    db = cantools.database.load_file(str(dbc_file))
    names = {m.name for m in db.messages}
    assert {"status", "heartbeat", "voltages", "battery_states", "dm1", "control"} <= names
    assert db.get_message_by_name("parameters").is_multiplexed()
    assert db.get_message_by_name("voltages").get_signal_by_name("i12").offset == -1600
    assert db.get_message_by_name("status").get_signal_by_name("imb").choices[1] == "active"
    exe = shutil.which("eqgw")
    assert exe, "the eqgw console script is installed"
    proc = subprocess.run(
        [exe, "decode", str(FIXTURE), "--only", "component_id"],
        capture_output=True,
        text=True,
        check=True,
    )
    assert [json.loads(x)["fields"]["text"] for x in proc.stdout.splitlines()] == [
        "EQ8001",
        "EQ7001",
    ]
