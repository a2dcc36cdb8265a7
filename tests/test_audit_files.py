"""The audit log's growth and the files' modes: requests without a valid key are counted into
one audit row per action and flush instead of one row each; entries older than the retention
are deleted; SQLite databases and forwarder buffers are created 0600 (their WAL and SHM too)."""

from __future__ import annotations

import asyncio
import os
import stat
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from sqlalchemy import Engine, event, select, text

from eqgw.forward.buffer import FrameBuffer
from eqgw.ingest.journal import RowJournal
from eqgw.ingest.rows import UnitRow
from eqgw.security import repository as q
from eqgw.security.audit import prune_audit
from eqgw.store.api_models import AuditEntry
from eqgw.store.engine import create_engine
from eqgw.store.migrate import upgrade_engine
from tests.api_helpers import served, wait_for


def _anonymous(engine: Engine) -> list[dict[str, Any]]:
    """Refusals of requests without a key (not the gateway's own commands' outcomes)."""
    with engine.connect() as conn:
        rows = conn.execute(
            select(AuditEntry).where(AuditEntry.key_id.is_(None), AuditEntry.outcome == "refused")
        )
        return [dict(r._mapping) for r in rows]


async def test_anonymous_refusals_do_not_grow_the_audit_log(db_url: str) -> None:
    """600 writes without a key: 600 refusals, one audit row saying 600 (it was 600 rows)."""
    async with served(db_url, vehicles=1) as s:
        body = {"unit": 30, "equalizer_on": True}
        for i in range(600):
            headers = {"Authorization": "Bearer eqgw_wrong"} if i % 2 else {}
            r = await s.client.post("/api/v1/vehicles/SIM-001/commands", json=body, headers=headers)
            assert r.status_code == 401
        await asyncio.to_thread(s.rt.audit_log.refusals.flush, s.rt.engine)
        rows = _anonymous(s.rt.engine)
        assert len(rows) == 1, len(rows)
        row = rows[0]
        assert row["action"] == "POST /vehicles/{vehicle_id}/commands"
        assert row["status_code"] == 401 and row["outcome"] == "refused"
        assert row["request"]["count"] == 600 and row["vehicle_id"] == "SIM-001"
        assert row["request"]["first_ts"] <= row["request"]["last_ts"]
        assert "600 request(s) without a valid key" in row["detail"]
        # Counted since the last flush, written at shutdown too.
        for _ in range(5):
            await s.client.post("/api/v1/keys", json={"name": "x", "role": "viewer"})
    engine = create_engine(db_url)
    try:
        rows = _anonymous(engine)
        assert sorted(r["request"]["count"] for r in rows) == [5, 600]
    finally:
        engine.dispose()


def test_audit_retention_deletes_old_entries(engine: Engine) -> None:
    now = time.time()
    entry = {"action": "key.create", "outcome": "accepted", "status_code": 201}
    with engine.begin() as conn:
        for age_days in (400, 366, 364, 1, 0):
            q.add_audit(conn, {**entry, "ts": now - age_days * 86400, "detail": str(age_days)})
    assert prune_audit(engine, 365, batch=1) == 2  # batches of one: the loop runs out
    with engine.connect() as conn:
        kept = sorted(int(r["detail"]) for r in q.list_audit(conn))
    assert kept == [0, 1, 364]
    assert prune_audit(engine, 0) == 0  # 0 keeps everything
    with engine.connect() as conn:
        assert len(q.list_audit(conn)) == 3


def test_audit_retention_told_to_stop_ends_before_its_next_transaction(engine: Engine) -> None:
    """A gateway that stops mid-prune tells it to end (eqgw.tasks.in_thread_until_stopped):
    what it deleted stays deleted, it opens no further transaction, the next prune goes on."""
    now = time.time()
    entry = {"action": "key.create", "outcome": "accepted", "status_code": 201}
    with engine.begin() as conn:
        for i in range(5):
            q.add_audit(conn, {**entry, "ts": now - 400 * 86400 + i, "detail": str(i)})
    stop = threading.Event()
    begins: list[int] = []

    @event.listens_for(engine, "begin")
    def _begin(_conn: Any) -> None:
        begins.append(1)
        if len(begins) == 2:
            stop.set()  # asked while the second batch's transaction runs

    try:
        assert prune_audit(engine, 365, batch=1, stop=stop) == 2
    finally:
        event.remove(engine, "begin", _begin)
    assert len(begins) == 2  # no third transaction
    assert prune_audit(engine, 365, batch=1) == 3  # the next prune takes the rest
    stop.set()
    assert prune_audit(engine, 365, stop=stop) == 0  # told before it began: nothing done


async def test_a_running_gateway_applies_the_retention(
    db_url: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The gateway's housekeeping task deletes entries past EQGW_API_AUDIT_RETENTION_DAYS
    (its hourly round made short here) and writes the anonymous counts on its own."""
    import eqgw.security.lifespan as upkeep

    monkeypatch.setattr(upkeep, "KEY_FLUSH_S", 0.1)
    monkeypatch.setattr(upkeep, "AUDIT_PRUNE_S", 0.3)
    monkeypatch.setattr(upkeep, "REFUSALS_FLUSH_S", 0.3)
    async with served(db_url, vehicles=1, audit_retention_days=30) as s:
        entry = {"action": "key.create", "outcome": "accepted", "status_code": 201}
        now = time.time()

        def add(conn: Any) -> None:
            q.add_audit(conn, {**entry, "ts": now - 31 * 86400, "detail": "old"})
            q.add_audit(conn, {**entry, "ts": now - 29 * 86400, "detail": "recent"})

        await s.rt.db(add)
        await s.client.get("/api/v1/vehicles")  # no key: 401, not audited (a read)
        await s.client.post("/api/v1/keys", json={"name": "x", "role": "viewer"})

        async def done() -> bool:
            details = {r["detail"] for r in await s.rt.db(q.list_audit)}
            return "old" not in details and any(
                d and d.startswith("1 request(s) without a valid key") for d in details
            )

        await wait_for(done, timeout=20, what="the old entry pruned, the refusal written")
        assert "recent" in {r["detail"] for r in await s.rt.db(q.list_audit)}


@pytest.fixture
def umask_022() -> Iterator[None]:
    old = os.umask(0o022)  # the usual umask, under which SQLite itself makes files 0644
    try:
        yield
    finally:
        os.umask(old)


def _mode(path: Path) -> int:
    return stat.S_IMODE(path.stat().st_mode)


def test_sqlite_database_files_are_private(tmp_path: Path, umask_022: None) -> None:
    db = tmp_path / "eqgw.db"
    engine = create_engine(f"sqlite:///{db}")
    try:
        upgrade_engine(engine)
        with engine.begin() as conn:
            conn.execute(text("CREATE TABLE t (x INTEGER)"))
        with engine.connect() as conn:  # WAL and SHM exist while a connection is open
            conn.execute(text("SELECT 1"))
            for path in (db, Path(f"{db}-wal"), Path(f"{db}-shm")):
                assert path.exists(), path
                assert _mode(path) == 0o600, (path, oct(_mode(path)))
    finally:
        engine.dispose()


def test_forwarder_buffer_files_are_private(tmp_path: Path, umask_022: None) -> None:
    path = tmp_path / "buffer.db"
    with FrameBuffer(path) as buf:
        buf.add([(time.time(), 0x18FFD61E, b"\x01\x02", 1)])
        for p in (path, Path(f"{path}-wal"), Path(f"{path}-shm")):
            assert p.exists(), p
            assert _mode(p) == 0o600, (p, oct(_mode(p)))


def test_writer_journal_files_are_private(tmp_path: Path, umask_022: None) -> None:
    journal = RowJournal.open(tmp_path, f"sqlite:///{tmp_path / 'eqgw.db'}")
    try:
        journal.append([UnitRow(("V1/can0", 30), "V1")])
        for p in (journal.path, Path(f"{journal.path}-wal"), Path(f"{journal.path}-shm")):
            if p.exists():
                assert _mode(p) == 0o600, (p, oct(_mode(p)))
        assert _mode(journal.path) == 0o600
    finally:
        journal.close()
