"""Database outages during live ingest: PostgreSQL stopped and started, SQLite locked."""

from __future__ import annotations

import asyncio
import glob
import os
import shutil
import socket
import subprocess
import tempfile
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from sqlalchemy import text

from eqgw.bus.config import BusConfig
from eqgw.bus.reader import BusReader
from eqgw.config import MonitorSettings, Settings, WriterSettings
from eqgw.ingest import events
from eqgw.ingest.pipeline import BusBinding, IngestPipeline
from eqgw.ingest.service import IngestService
from eqgw.ingest.writer import BatchedWriter
from eqgw.store.engine import create_engine
from eqgw.store.migrate import upgrade_engine
from eqgw.store.writes import load_unit_ids

PG_BINS = sorted(glob.glob("/usr/lib/postgresql/*/bin"))


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port: int = s.getsockname()[1]
        return port


class ThrowawayCluster:
    """A private PostgreSQL cluster in a temp dir, so the shared server is never stopped."""

    def __init__(self, bindir: str) -> None:
        self.bindir = bindir
        self.dir = Path(tempfile.mkdtemp(prefix="eqgw-pg-"))
        self.data = self.dir / "data"
        self.port = _free_port()
        self._as_postgres = os.geteuid() == 0  # initdb refuses to run as root
        if self._as_postgres:
            shutil.chown(self.dir, "postgres", "postgres")

    def _run(self, *args: str) -> None:
        cmd = [f"{self.bindir}/{args[0]}", *args[1:]]
        if self._as_postgres:
            cmd = ["runuser", "-u", "postgres", "--", *cmd]
        subprocess.run(cmd, check=True, capture_output=True, timeout=120)

    @property
    def url(self) -> str:
        return f"postgresql+psycopg://postgres@127.0.0.1:{self.port}/postgres"

    def init(self) -> None:
        self._run("initdb", "-D", str(self.data), "-A", "trust", "-U", "postgres", "--no-sync")

    def start(self) -> None:
        opts = f"-p {self.port} -k {self.dir} -c listen_addresses=127.0.0.1 -c fsync=off"
        self._run(
            "pg_ctl", "-D", str(self.data), "-o", opts, "-l", str(self.dir / "log"), "-w", "start"
        )

    def stop(self) -> None:
        self._run("pg_ctl", "-D", str(self.data), "-m", "fast", "-w", "stop")

    def destroy(self) -> None:
        try:
            self.stop()
        except subprocess.CalledProcessError:
            pass  # already stopped
        shutil.rmtree(self.dir, ignore_errors=True)


@pytest.fixture
def throwaway_pg() -> Iterator[ThrowawayCluster]:
    if not PG_BINS or not shutil.which("runuser"):
        pytest.skip("no PostgreSQL binaries in /usr/lib/postgresql/*/bin to run a private cluster")
    cluster = ThrowawayCluster(PG_BINS[-1])
    try:
        cluster.init()
        cluster.start()
    except subprocess.CalledProcessError as exc:
        cluster.destroy()
        pytest.skip(f"cannot start a private PostgreSQL cluster: {exc.stderr!r}")
    try:
        yield cluster
    finally:
        cluster.destroy()


async def _wait_for(cond, timeout: float, what: str) -> None:  # type: ignore[no-untyped-def]
    deadline = time.monotonic() + timeout
    while not cond():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for {what}")
        await asyncio.sleep(0.1)


@pytest.mark.postgres
@pytest.mark.slow
@pytest.mark.timeout(900)  # a private PostgreSQL cluster made, stopped and restarted
async def test_postgres_restart_during_live_ingest_loses_nothing(
    throwaway_pg: ThrowawayCluster,
) -> None:
    from eqgw.sim.fleet import SimulatedFleet

    fleet = SimulatedFleet(3, seed=4, speed=5.0)
    buses = [
        BusConfig(name=f"{name}/can0", vehicle_id=name, interface="virtual", channel=channel)
        for name, channel in fleet.channels.items()
    ]
    settings = Settings(
        database_url=throwaway_pg.url,
        vehicles=[{"id": name} for name in fleet.names],
        buses=buses,
        writer=WriterSettings(flush_ms=100, retry_initial_s=0.1, retry_max_s=0.5),
    )
    readers = [BusReader(cfg) for cfg in buses]
    service = IngestService(settings, sources=readers, retention=False)
    sub = service.hub.subscribe([events.RECORD], maxsize=1_000_000)
    await service.start()
    await fleet.start()
    try:
        writer = service.writer
        await _wait_for(lambda: writer.status().committed_rows > 200, 60, "first commits")
        await asyncio.to_thread(throwaway_pg.stop)
        await _wait_for(lambda: writer.status().failures >= 2, 60, "the writer to notice")
        # Ingest keeps accepting while the database is away: what is held grows.
        noticed = writer.status().pending_rows
        await _wait_for(lambda: writer.status().pending_rows > noticed, 60, "rows held meanwhile")
        held = writer.status().pending_rows
        await asyncio.to_thread(throwaway_pg.start)
        await _wait_for(lambda: writer.status().consecutive_failures == 0, 60, "recovery")
        await asyncio.sleep(1.0)
    finally:
        await fleet.stop()
        left = await service.stop()
    status = service.writer.status()
    assert left == 0
    assert status.refused_rows == 0
    assert status.failures >= 2
    assert held > 0

    seen: set[tuple[str, int, float]] = set()
    battery: set[tuple[str, int, float, int]] = set()
    while (event := sub.get_nowait()) is not None:
        rec = event.data
        if rec["name"] == "voltages":
            seen.add((event.unit.bus, event.unit.sa, rec["ts"]))
        elif rec["name"] == "battery_states":
            battery.add((event.unit.bus, event.unit.sa, rec["ts"], rec["fields"]["index"]))
    assert len(seen) > 20
    engine = create_engine(throwaway_pg.url)
    try:
        with engine.connect() as conn:
            ids = {v: k for k, v in load_unit_ids(conn).items()}
            stored = {
                (*ids[u], ts)
                for u, ts in conn.execute(text("SELECT unit_id, ts FROM measurements"))
            }
            stored_b = {
                (*ids[u], ts, idx)
                for u, ts, idx in conn.execute(text("SELECT unit_id, ts, idx FROM battery_states"))
            }
    finally:
        engine.dispose()
    assert seen - stored == set()
    assert battery - stored_b == set()


def _voltages_msg(ts: float, channel: str, v12: float) -> object:
    import can

    from eqgw.protocol.encode import encode

    ((can_id, data),) = encode(
        "voltages", {"v12": v12, "v24": 2 * v12, "i12": 1.0, "i24": 2.0}, sa=30
    )
    return can.Message(timestamp=ts, arbitration_id=can_id, data=data, channel=channel)


def test_sqlite_locked_writer_retries_and_keeps_rows(
    sqlite_url: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Another process holds the write lock longer than busy_timeout: the writer keeps the
    batch, reports the failure, and commits everything once the lock is gone."""
    import eqgw.store.engine as store_engine

    engine = create_engine(sqlite_url)
    upgrade_engine(engine)
    # Read when a connection is opened, which the writer's engine does lazily (in its thread,
    # after start): kept for the whole test, not only while the engine is created (each
    # attempt then waited the default 10 s, and two failures could take past the deadline).
    monkeypatch.setattr(store_engine, "SQLITE_BUSY_TIMEOUT_MS", 50)
    wengine = create_engine(sqlite_url)
    writer = BatchedWriter(
        wengine, WriterSettings(flush_ms=20, retry_initial_s=0.05, retry_max_s=0.2)
    )
    pipeline = IngestPipeline([BusBinding("B/can0", "B")], monitor=MonitorSettings())
    writer.start()
    blocker = engine.raw_connection()
    try:
        blocker.driver_connection.execute("BEGIN EXCLUSIVE")  # type: ignore[union-attr]
        for i in range(500):
            pipeline.process(_voltages_msg(1000.0 + i, "B/can0", 12.0 + i / 1000))
        pipeline.finish()
        assert writer.offer(pipeline.take_rows())
        deadline = time.monotonic() + 30
        while writer.status().failures < 2:
            assert time.monotonic() < deadline, "writer never hit the lock"
            time.sleep(0.05)
        assert writer.status().pending_rows > 0
        assert "locked" in (writer.status().last_error or "")
        # The lag is the age of the oldest row held, and grows while the lock is held.
        lag = writer.status().lag_s
        time.sleep(0.2)
        assert writer.status().lag_s >= lag + 0.15 and lag > 0
    finally:
        blocker.driver_connection.execute("ROLLBACK")  # type: ignore[union-attr]
        blocker.close()
    assert writer.flush(timeout=30)
    assert writer.status().lag_s == 0.0  # nothing waits
    assert writer.stop() == 0
    with engine.connect() as conn:
        assert conn.execute(text("SELECT count(*) FROM measurements")).scalar() == 500
    engine.dispose()
    wengine.dispose()


def test_writer_memory_bound_refuses_and_blocks(sqlite_url: str) -> None:
    """Past max_pending_rows, offer() refuses (counted) and put() waits for room."""
    engine = create_engine(sqlite_url)
    upgrade_engine(engine)
    writer = BatchedWriter(engine, WriterSettings(max_pending_rows=10, flush_ms=10))
    rows = [("vehicle", f"V{i}", {"id": f"V{i}", "name": f"V{i}", "depot": None}) for i in range(8)]
    assert writer.offer(rows)  # not started: nothing drains
    assert not writer.offer(rows)
    assert writer.status().refused_rows == 8
    assert not writer.put(rows, timeout=0.05)
    done = threading.Event()

    def late_put() -> None:
        writer.put(rows)  # blocks until the writer drains the first rows
        done.set()

    t = threading.Thread(target=late_put)
    t.start()
    writer.start()
    t.join(30)
    assert done.is_set()
    assert writer.flush(timeout=30)
    assert writer.status().backpressure_waits >= 1
    assert writer.stop() == 0
    engine.dispose()
