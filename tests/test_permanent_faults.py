"""Faults that no retry cures end the process with one line and a non-zero exit; faults that
heal are retried. `eqgw serve` and `eqgw forward` as subprocesses on damaged, read-only and
misnamed databases; the supervisor on a real read-only and a real locked SQLite file."""

from __future__ import annotations

import asyncio
import contextlib
import os
import sqlite3
import subprocess
import uuid
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from eqgw.supervisor import FatalError, Supervisor, permanent_fault
from tests.conftest import PG_ADMIN_URL
from tests.proc_helpers import ROOT, eqgw, mounted, run


def _run(tmp_path: Path, *args: str, url: str) -> Any:
    env = {k: v for k, v in os.environ.items() if not k.startswith("EQGW_")}
    env.update({"PYTHONPATH": str(ROOT), "EQGW_DATABASE_URL": url, "EQGW_FORWARD_KEY": "k" * 32})
    return run(eqgw(*args), tmp_path, env, timeout=90)


def _zeroed(path: Path) -> Path:
    path.write_bytes(b"\0" * 16384)
    return path


def _truncated(path: Path) -> Path:
    db = sqlite3.connect(path)
    with db:
        db.execute("CREATE TABLE filler (x BLOB)")
        db.executemany("INSERT INTO filler VALUES (?)", [(os.urandom(400),) for _ in range(500)])
    db.close()
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    return path


def _healthy(path: Path) -> Path:
    db = sqlite3.connect(path)
    db.execute("PRAGMA journal_mode=WAL")
    db.execute("CREATE TABLE t (x)")
    db.close()
    return path


@contextlib.contextmanager
def _read_only_mount(tmp_path: Path) -> Iterator[Path]:
    """A folder holding a SQLite file, bind-mounted read-only (root only; skipped elsewhere)."""
    folder = tmp_path / "ro"
    folder.mkdir()
    _healthy(folder / "eqgw.db")
    bind, read_only = ["--bind", str(folder), str(folder)], ["-o", "remount,ro,bind", str(folder)]
    with mounted(folder, bind, read_only, what="read-only") as path:
        yield path


def _one_line_exit(r: Any, word: str) -> None:
    lines = [line for line in r.stderr.splitlines() if line.strip()]
    assert r.returncode not in (0, None), (r.returncode, r.stderr)
    assert "Traceback" not in r.stderr + r.stdout, r.stderr
    assert "retrying" not in r.stderr, r.stderr  # said once, never retried
    assert len(lines) == 1 and word in lines[0], r.stderr


@pytest.mark.parametrize(
    ("make", "word"),
    [(_zeroed, "file is not a database"), (_truncated, "database disk image is malformed")],
)
def test_serve_on_a_damaged_sqlite_file_exits_in_one_line(
    tmp_path: Path, make: Any, word: str
) -> None:
    db = make(tmp_path / "eqgw.db")
    r = _run(tmp_path, "serve", "--port", "0", url=f"sqlite:///{db}")
    _one_line_exit(r, word)


def test_serve_on_a_read_only_sqlite_file_exits_in_one_line(tmp_path: Path) -> None:
    db = _healthy(tmp_path / "eqgw.db")
    # Root writes whatever the file mode says: as root the file is made immutable instead.
    if os.geteuid() == 0:
        done = subprocess.run(["chattr", "+i", str(db)], capture_output=True, text=True)
        if done.returncode != 0:
            pytest.skip(f"cannot make a file read-only for root here: {done.stderr.strip()}")
    else:
        db.chmod(0o444)
    try:
        r = _run(tmp_path, "serve", "--port", "0", url=f"sqlite:///{db}")
    finally:
        if os.geteuid() == 0:
            subprocess.run(["chattr", "-i", str(db)], check=False)
    _one_line_exit(r, "readonly database")


def test_serve_on_a_read_only_mount_exits_in_one_line(tmp_path: Path) -> None:
    with _read_only_mount(tmp_path) as folder:
        r = _run(tmp_path, "serve", "--port", "0", url=f"sqlite:///{folder / 'eqgw.db'}")
    _one_line_exit(r, "unable to open database file")


@pytest.mark.postgres
def test_serve_on_a_misspelled_postgres_database_exits_in_one_line(
    tmp_path: Path, pg_url: str
) -> None:
    misspelled = PG_ADMIN_URL.rsplit("/", 1)[0] + f"/tset_{uuid.uuid4().hex[:6]}"
    r = _run(tmp_path, "serve", "--port", "0", url=misspelled)
    _one_line_exit(r, "does not exist")


def test_forward_on_a_damaged_buffer_exits_in_one_line(tmp_path: Path) -> None:
    buffer = _zeroed(tmp_path / "fwd.db")
    r = _run(
        tmp_path, "forward", "--bus", "virtual:x", "--vehicle", "V", "--to",
        "http://127.0.0.1:9/api/v1", "--buffer", str(buffer), url="sqlite://",
    )  # fmt: skip
    _one_line_exit(r, "file is not a database")


async def test_supervisor_ends_on_a_read_only_file_and_retries_a_locked_one(
    tmp_path: Path,
) -> None:
    """A loop writing a SQLite file opened read-only fails for good (once, on_fatal); a loop
    writing a file another connection holds the write lock of is retried until it is free."""
    path = _healthy(tmp_path / "x.db")
    fatal: list[FatalError] = []
    sup = Supervisor(backoff=(0.05, 0.2), on_fatal=fatal.append)

    async def write_read_only() -> None:
        db = sqlite3.connect(f"file:{path}?mode=ro", uri=True)
        try:
            db.execute("INSERT INTO t VALUES (1)")
        finally:
            db.close()

    holder = sqlite3.connect(path, isolation_level=None)
    holder.execute("BEGIN IMMEDIATE")
    tries = 0

    async def write_locked() -> None:
        nonlocal tries
        tries += 1
        db = sqlite3.connect(path, timeout=0.01, isolation_level=None)
        try:
            db.execute("INSERT INTO t VALUES (2)")
        finally:
            db.close()

    try:
        sup.start("read-only", write_read_only)
        locked = sup.start("locked", write_locked)
        for _ in range(200):
            if tries >= 3 and fatal:
                break
            await asyncio.sleep(0.02)
        assert [f.task for f in fatal] == ["read-only"]
        st = sup.get("read-only")
        assert st is not None and st.state == "failed" and "readonly" in (st.last_error or "")
        busy = sup.get("locked")
        assert busy is not None and busy.state in ("backoff", "running") and tries >= 3
        assert "locked" in (busy.last_error or "")
        holder.execute("ROLLBACK")  # the lock is released: the next try succeeds
        async with asyncio.timeout(30):
            await locked
        assert sup.get("locked").state == "done"  # type: ignore[union-attr]
    finally:
        holder.close()
        await sup.stop()
    assert len(fatal) == 1


def test_permanent_fault_classification() -> None:
    """The driver errors seen on damaged, read-only and misnamed databases, and some that
    heal (disk full, locked, refused connection)."""

    def sqlite_error(code: int, msg: str) -> sqlite3.Error:
        exc = sqlite3.OperationalError(msg)
        exc.sqlite_errorcode = code  # type: ignore[attr-defined]
        return exc

    assert permanent_fault(sqlite_error(26, "file is not a database")) == "SQLITE_NOTADB"
    assert permanent_fault(sqlite_error(11, "malformed")) == "SQLITE_CORRUPT"
    assert permanent_fault(sqlite_error(8 | (1 << 8), "readonly")) == "SQLITE_READONLY"
    assert permanent_fault(sqlite_error(13, "database or disk is full")) is None
    assert permanent_fault(sqlite_error(5, "database is locked")) is None
    assert permanent_fault(ConnectionRefusedError()) is None
    wrapped = RuntimeError("batch failed")
    wrapped.__cause__ = sqlite_error(26, "file is not a database")
    assert permanent_fault(wrapped) == "SQLITE_NOTADB"
