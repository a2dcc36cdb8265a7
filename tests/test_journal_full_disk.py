"""A stop on a full disk: `eqgw serve` with its SQLite database, and the journal beside it, on a
small filesystem (a tmpfs) that fills up. The database write fails, the rows are held, the
journal cannot take them during the outage either; at SIGTERM the journal takes them in the
space it reserved at start, or the second journal location does, or, when neither can, the
process says how many rows it lost and exits non-zero."""

from __future__ import annotations

import contextlib
import os
import re
import signal
import uuid
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx

from eqgw.ingest.journal import RowJournal
from eqgw.ingest.rows import VehicleRow
from tests.proc_helpers import Process, eqgw, free_port, mounted, wait_until
from tests.support import web

TOKEN = "journal-full-disk-metrics"


@contextlib.contextmanager
def small_disk(tmp_path: Path, size: str) -> Iterator[Path]:
    mnt = tmp_path / f"disk-{uuid.uuid4().hex[:6]}"
    mnt.mkdir()
    with mounted(mnt, ["-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(mnt)], what="a tmpfs"):
        yield mnt


def _fill(disk: Path) -> None:
    with contextlib.suppress(OSError), (disk / "filler").open("wb") as f:
        while True:
            f.write(b"\0" * 16384)
            f.flush()


def _writer(base: str) -> dict[str, Any] | None:
    try:
        r = web.get(f"{base}/readyz", headers={"Authorization": f"Bearer {TOKEN}"}, timeout=5)
        body: dict[str, Any] = r.json()
    except (httpx.HTTPError, ValueError):
        return None
    return (body.get("database") or {}).get("writer")


def _stop_on_a_full_disk(tmp_path: Path, disk: Path, env: dict[str, str]) -> tuple[int, str, int]:
    """Serve a simulated fleet on `disk`, fill it, wait for rows held, SIGTERM: returns the
    exit status, the output and the rows the writer held just before the stop."""
    port = free_port()
    base = f"http://127.0.0.1:{port}"
    proc = Process(
        eqgw("serve", "--simulate", "4"),
        tmp_path,
        {
            "EQGW_DATABASE_URL": f"sqlite:///{disk / 'db.sqlite'}",
            "EQGW_API_PORT": str(port),
            "EQGW_API_METRICS_TOKEN": TOKEN,
            "EQGW_WRITER__SPILL_AFTER_S": "0.5",
            **env,
        },
    )
    try:
        wait_until(lambda: (_writer(base) or {}).get("state") == "idle", 120, "the writer idle")
        _fill(disk)
        held = wait_until(
            lambda: ((_writer(base) or {}).get("pending_rows") or 0) >= 50,
            60,
            "rows held while the disk is full",
        )
        held = (_writer(base) or {}).get("pending_rows") or held
    finally:
        code = proc.stop()
    return code, proc.output(), int(held)


def _journal_rows(folder: Path, disk: Path) -> int:
    os.unlink(disk / "filler")  # room to open it
    journal = RowJournal.open(folder, f"sqlite:///{disk / 'db.sqlite'}")
    try:
        return journal.rows
    finally:
        journal.close(remove=False)


def test_a_stop_on_a_full_disk_writes_into_the_space_reserved(tmp_path: Path) -> None:
    with small_disk(tmp_path, "8m") as disk:
        code, out, held = _stop_on_a_full_disk(
            tmp_path, disk, {"EQGW_WRITER__JOURNAL_RESERVE_MB": "2"}
        )
        assert "LOST" not in out and "unwritten" not in out, out[-3000:]
        assert code in (0, -signal.SIGTERM), out[-3000:]
        assert "bytes of reserve freed" in out, out[-3000:]
        assert _journal_rows(disk, disk) >= held


def test_a_stop_the_journal_cannot_take_goes_to_the_second_location(tmp_path: Path) -> None:
    second = tmp_path / "second"
    with small_disk(tmp_path, "8m") as disk:
        code, out, held = _stop_on_a_full_disk(
            tmp_path,
            disk,
            {
                "EQGW_WRITER__JOURNAL_RESERVE_MB": "0",
                "EQGW_WRITER__JOURNAL_FALLBACK_DIR": str(second),
            },
        )
        assert code in (0, -signal.SIGTERM) and "LOST" not in out, out[-3000:]
        assert _journal_rows(second, disk) >= held


def test_rows_no_journal_can_take_are_counted_lost_and_the_exit_is_not_0(tmp_path: Path) -> None:
    with small_disk(tmp_path, "8m") as disk:
        code, out, held = _stop_on_a_full_disk(
            tmp_path, disk, {"EQGW_WRITER__JOURNAL_RESERVE_MB": "0"}
        )
    assert code == 1, out[-3000:]
    lost = re.search(r"writer stopped: (\d+) rows LOST, no journal could take them", out)
    assert lost is not None and int(lost.group(1)) >= held, out[-3000:]
    assert f"{lost.group(1)} rows lost at stop" in out


def test_the_next_start_takes_over_what_the_second_location_holds(tmp_path: Path) -> None:
    url = f"sqlite:///{tmp_path / 'db.sqlite'}"
    second = RowJournal.open(tmp_path / "second", url)
    second.append(
        [
            VehicleRow("V", {"id": "V", "name": "V", "depot": None}),
            VehicleRow("W", {"id": "W", "name": "W", "depot": None}),
        ]
    )
    second.close()
    main = RowJournal.open(tmp_path / "main", url)
    try:
        assert main.reserve(1_000_000) == 1_000_000 and main.reserved_bytes() >= 1_000_000
        assert main.adopt_from(tmp_path / "second", url) == 2
        assert main.rows == 2 and main.inherited_rows == 2  # replayed first, as the journal's
        assert not list((tmp_path / "second").glob("eqgw-journal-*"))
    finally:
        main.close()
    assert not main.reserve_path.exists()  # given back at the stop
