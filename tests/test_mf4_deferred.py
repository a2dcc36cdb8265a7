"""asammdf (the mf4 extra) is loaded when an MF4 log is read or written, not at `import eqgw`:
checked in fresh interpreters, where `eqgw` is imported before `can` as in the `eqgw` command."""

from __future__ import annotations

import importlib.util
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

# Found, not imported: an import here would load asammdf (numpy, pandas, sympy) into every test
# process at collection (tests/conftest.py).
if importlib.util.find_spec("asammdf") is None:
    pytest.skip("asammdf (the mf4 extra) is not installed", allow_module_level=True)

_ROUND_TRIP = """
import sys
from typing import NamedTuple
import eqgw.main  # the gateway's whole import: the API, ingest, every domain
assert "asammdf" not in sys.modules, "asammdf imported by eqgw.main"
import can
from eqgw.bus.export import LogExport
from eqgw.bus.replay import open_log_reader
assert "asammdf" not in sys.modules, "asammdf imported before an MF4 log was asked for"

class Frame(NamedTuple):
    ts: float
    can_id: int
    is_extended: bool
    is_remote: bool
    is_error: bool
    data: bytes

frames = [Frame(1700000000.0 + i / 8, 0x18FF5027 + i, True, False, False, bytes([i] * 8))
          for i in range(40)]
export = LogExport("mf4")
export.write([(0, f) for f in frames])
export.finish()
data = b"".join(iter(lambda: export.read(), b""))
export.close()
path = sys.argv[1]
with open(path, "wb") as out:
    out.write(data)
assert "asammdf" in sys.modules
reader = open_log_reader(path)
got = [(m.timestamp, m.arbitration_id, bytes(m.data)) for m in reader]
assert got == [(f.ts, f.can_id, f.data) for f in frames], got[:3]
# python-can's own entry points see the MF4 support too.
assert can.MF4Reader is can.io.player.MESSAGE_READERS[".mf4"]
assert len(list(can.LogReader(path))) == 40
print("ok", len(got))
"""


def _run(code: str, *args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-c", textwrap.dedent(code), *args],
        capture_output=True,
        text=True,
        timeout=120,
    )


def test_mf4_is_written_and_read_back_after_a_start_without_asammdf(tmp_path: Path) -> None:
    done = _run(_ROUND_TRIP, str(tmp_path / "round.mf4"))
    assert done.returncode == 0, done.stderr
    assert done.stdout.split() == ["ok", "40"]


def test_without_asammdf_mf4_is_refused_with_the_extra_to_install(tmp_path: Path) -> None:
    """Where asammdf cannot be imported (the extra not installed), the export says which extra
    to install and a .mf4 log cannot be read, in one line, nothing else breaking."""
    log = tmp_path / "x.mf4"
    log.write_bytes(b"MDF     4.10    ")
    code = """
    import sys
    sys.modules["asammdf"] = None  # as if not installed
    import eqgw.main
    from eqgw.bus.export import ExportError, LogExport, mf4_available
    from eqgw.bus.errors import LogFileError
    from eqgw.bus.replay import open_log_reader
    assert not mf4_available()
    try:
        LogExport("mf4")
    except ExportError as exc:
        print("export:", exc)
    try:
        open_log_reader(sys.argv[1])
    except LogFileError as exc:
        print("read:", "eqgw[mf4]" in str(exc) or "asammdf" in str(exc))
    LogExport("blf").close()
    """
    done = _run(code, str(log))
    assert done.returncode == 0, done.stderr
    assert done.stdout.splitlines() == [
        "export: MF4 needs asammdf: pip install 'eqgw[mf4]'",
        "read: True",
    ]
