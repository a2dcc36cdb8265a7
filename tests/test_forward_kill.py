"""`eqgw forward` killed with SIGKILL in the middle of uploading its backlog, then started again
on the same buffer: every frame still reaches the central service once. The vehicle is a
simulated one served over socketcand; the central service is `eqgw serve` in a subprocess."""

from __future__ import annotations

import asyncio
import sqlite3
from pathlib import Path

from eqgw.bus.socketcand_server import SocketcandServer
from eqgw.store.engine import create_engine
from tests.forward_helpers import (
    VEHICLE,
    RecordedVehicle,
    async_wait,
    central_config,
    replay_counts,
    start_central,
    stream_row,
    table_counts,
)
from tests.proc_helpers import Process, eqgw, free_port


def _last_seq(path: Path) -> int:
    """The newest sequence number the forwarder's buffer gave out (read beside it: WAL)."""
    if not path.exists():
        return 0
    try:
        with sqlite3.connect(f"file:{path}?mode=ro", uri=True, timeout=5) as db:
            row = db.execute("SELECT seq FROM sqlite_sequence WHERE name = 'frames'").fetchone()
    except sqlite3.OperationalError:
        return 0  # not created yet
    return int(row[0]) if row else 0


async def _drive(veh: RecordedVehicle, seconds: float, step: float = 5.0) -> None:
    t = 0.0
    while t < seconds:
        veh.fleet.advance(step)
        t += step
        await asyncio.sleep(0.01)  # the socketcand server runs on this loop


async def test_forwarder_killed_mid_upload_restarts_and_delivers_once(
    db_url: str, tmp_path: Path
) -> None:
    config, key = central_config(tmp_path, db_url)
    port = free_port()
    veh = RecordedVehicle(seed=5)
    server = SocketcandServer("127.0.0.1", 0, {VEHICLE: veh.channel})
    buffer = tmp_path / "fwd.db"
    argv = eqgw(
        "forward",
        "--bus", f"socketcand:{VEHICLE}",
        "--option", "host=127.0.0.1",
        "--option", f"port={0}",
        "--sa", ",".join(str(sa) for sa in veh.sas),
        "--vehicle", VEHICLE,
        "--bus-name", VEHICLE,
        "--to", f"http://127.0.0.1:{port}/api/v1",
        "--buffer", str(buffer),
        "--batch-frames", "10",
        "--backoff-max", "0.5",
    )  # fmt: skip
    env = {"EQGW_FORWARD_KEY": key}
    engine = create_engine(db_url)
    procs: list[Process] = []
    central: Process | None = None
    try:
        await server.start()
        argv[argv.index("port=0")] = f"port={server.port}"
        fwd = Process(argv, tmp_path, env)
        procs.append(fwd)
        await async_wait(lambda: "bus open" in fwd.output(), 60, "the forwarder's bus")
        await asyncio.sleep(0.5)
        veh.fleet.open()
        # Five simulated minutes buffered while the central service is not there yet.
        await _drive(veh, 300)
        n1 = len(veh.kept())
        await async_wait(lambda: _last_seq(buffer) == n1, 60, "every frame buffered")
        central = await asyncio.to_thread(start_central, tmp_path, config, port)

        def uploading() -> int:
            row = stream_row(engine)
            return row["acked_seq"] if row else 0

        await async_wait(uploading, 60, "the first acknowledged batch")
        await asyncio.to_thread(fwd.kill)
        at_kill = uploading()
        assert 0 < at_kill < n1, "the kill was meant to land in the middle of the backlog"
        # Started again on the same buffer: it resumes after the last acknowledgement.
        fwd = Process(argv, tmp_path, env)
        procs.append(fwd)
        await async_wait(lambda: "bus open" in fwd.output(), 60, "the restarted forwarder")
        await asyncio.sleep(0.5)
        await _drive(veh, 60)  # and it reads on
        n2 = len(veh.kept())
        await async_wait(lambda: uploading() == n2, 60, "everything acknowledged")
        assert await asyncio.to_thread(fwd.stop) == 0
        row = stream_row(engine)
        assert row is not None
        # Each sequence number decoded once: a batch re-sent after the kill was answered as
        # already stored (or cut at acked_seq), never decoded again.
        assert (row["acked_seq"], row["frames"], row["dropped"]) == (n2, n2, 0)
        assert _last_seq(buffer) == n2
    finally:
        for p in procs:
            await asyncio.to_thread(p.stop)
        if central is not None:
            await asyncio.to_thread(central.stop)
        await server.stop()
        veh.fleet.close()
        engine.dispose()
    assert table_counts(db_url) == replay_counts(veh.sent, tmp_path, veh.sas)
