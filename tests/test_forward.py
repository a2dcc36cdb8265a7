"""Edge forwarding: the central service down for minutes of simulated time and back, every
frame stored once; the buffer bound; the ingest role. Central: `eqgw serve` in a subprocess on
SQLite and PostgreSQL; forwarder: in-process, reading a simulated vehicle's virtual bus."""

from __future__ import annotations

import asyncio
from pathlib import Path

from eqgw.bus.config import BusConfig
from eqgw.forward.buffer import FrameBuffer
from eqgw.forward.uploader import Forwarder, UploadSettings
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
from tests.proc_helpers import Process, free_port


def _forwarder(
    veh: RecordedVehicle, buffer: FrameBuffer, port: int, key: str, batch: int = 200
) -> Forwarder:
    bus = BusConfig(
        name=f"{VEHICLE}/sim",
        vehicle_id=VEHICLE,
        interface="virtual",
        channel=veh.channel,
        bitrate=None,
        equalizer_sas=veh.sas,
    )
    upload = UploadSettings(
        url=f"http://127.0.0.1:{port}/api/v1",
        key=key,
        vehicle=VEHICLE,
        bus=VEHICLE,  # as `eqgw replay --vehicle SIM-001` names it: both share the units
        equalizer_sas=tuple(veh.sas),
        batch_frames=batch,
        backoff_initial_s=0.05,
        backoff_max_s=0.5,
        idle_poll_s=0.1,
    )
    return Forwarder(bus, buffer, upload)


async def _run_sim(veh: RecordedVehicle, fwd: Forwarder, seconds: float, step: float = 5.0):
    """Simulated time passes in steps; the forwarder reads along (it shares this loop)."""
    t = 0.0
    while t < seconds:
        veh.fleet.advance(step)
        t += step
        await asyncio.sleep(0.005)
    n = len(veh.kept())
    await async_wait(lambda: fwd.frames_kept == n, 30, "the forwarder to read every frame")


async def _start_central(tmp_path: Path, config: Path, port: int) -> Process:
    return await asyncio.to_thread(start_central, tmp_path, config, port)


async def test_central_down_for_minutes_then_back_every_frame_once(
    db_url: str, tmp_path: Path
) -> None:
    config, key = central_config(tmp_path, db_url)
    port = free_port()
    veh = RecordedVehicle(pick=3)  # two units in parallel, SA 30 and 31
    assert veh.sas == [30, 31]
    buffer = FrameBuffer(tmp_path / "fwd.db")
    engine = create_engine(db_url)
    fwd = _forwarder(veh, buffer, port, key)
    central: Process | None = None
    try:
        await fwd.start()
        await fwd.reader.wait_open(10)
        veh.fleet.open()
        # Five minutes of driving while the central service is unreachable.
        await _run_sim(veh, fwd, 300)
        n1 = len(veh.kept())
        assert n1 > 1000
        await async_wait(lambda: fwd.uploader.status().consecutive_failures >= 2, 30, "retries")
        assert buffer.status().rows == n1 and buffer.status().acked_seq == 0
        # Back: the backlog goes up in batches.
        central = await _start_central(tmp_path, config, port)
        await async_wait(lambda: buffer.status().acked_seq == n1, 60, "the backlog uploaded")
        assert buffer.status().rows == 0
        # A minute more online, then the central dies (SIGKILL) for two minutes.
        await _run_sim(veh, fwd, 60)
        central.kill()
        central = None
        await _run_sim(veh, fwd, 120)
        n2 = len(veh.kept())
        await async_wait(lambda: fwd.uploader.status().consecutive_failures >= 1, 30, "failure")
        central = await _start_central(tmp_path, config, port)
        await async_wait(lambda: buffer.status().acked_seq == n2, 60, "everything uploaded")
        row = stream_row(engine)
        assert row is not None
        # Every sequence number decoded exactly once, and the history is what a replay of the
        # same frames stores.
        assert (row["acked_seq"], row["frames"], row["dropped"]) == (n2, n2, 0)
        assert row["stream"] == buffer.stream and row["vehicle_id"] == VEHICLE
    finally:
        await fwd.stop()
        if central is not None:
            await asyncio.to_thread(central.stop)
        veh.fleet.close()
        buffer.close()
        engine.dispose()
    got = table_counts(db_url)
    want = replay_counts(veh.sent, tmp_path, veh.sas)
    assert got == want
    assert got["raw_frames"] > 0 and got["measurements"] > 0


async def test_buffer_full_drops_the_oldest_and_counts(tmp_path: Path) -> None:
    db_url = f"sqlite:///{tmp_path / 'central.db'}"
    config, key = central_config(tmp_path, db_url)
    port = free_port()
    veh = RecordedVehicle()
    buffer = FrameBuffer(tmp_path / "fwd.db", max_rows=300)
    fwd = _forwarder(veh, buffer, port, key, batch=100)
    engine = create_engine(db_url)
    central: Process | None = None
    try:
        await fwd.start()
        await fwd.reader.wait_open(10)
        veh.fleet.open()
        await _run_sim(veh, fwd, 300)  # central down: more than 300 frames
        kept = veh.kept()
        st = buffer.status()
        assert st.rows == 300 and st.last_seq == len(kept)
        assert st.dropped == len(kept) - 300
        # The newest 300 remain, in order.
        rows = buffer.peek(1000)
        assert [r[0] for r in rows] == list(range(len(kept) - 299, len(kept) + 1))
        assert [r[1] for r in rows] == [m.timestamp for m in kept[-300:]]
        central = await _start_central(tmp_path, config, port)
        await async_wait(lambda: buffer.status().rows == 0, 60, "the newest frames uploaded")
        row = stream_row(engine)
        assert row is not None
        # The central service knows what was lost, and took only what was left.
        assert (row["acked_seq"], row["frames"], row["dropped"]) == (len(kept), 300, st.dropped)
    finally:
        await fwd.stop()
        if central is not None:
            await asyncio.to_thread(central.stop)
        veh.fleet.close()
        buffer.close()
        engine.dispose()
    assert table_counts(db_url) == replay_counts(kept[-300:], tmp_path, veh.sas)


def test_buffer_bound_in_bytes_and_restart(tmp_path: Path) -> None:
    path = tmp_path / "b.db"
    with FrameBuffer(path, max_rows=10**6, max_bytes=40 * 10) as b:  # 10 frames of 8 bytes
        stream = b.stream
        assert b.add([(float(i), 0x18FFD61E, bytes(8), 1) for i in range(25)]) == 15
        assert (b.rows, b.dropped) == (10, 15)
        assert b.ack(20) == 5
    with FrameBuffer(path, max_rows=10**6, max_bytes=400) as b:  # after a restart
        st = b.status()
        assert (st.stream, st.rows, st.dropped, st.acked_seq, st.last_seq) == (
            stream,
            5,
            15,
            20,
            25,
        )
        b.ack(25)
        b.add([(99.0, 1, b"", 1)])
        assert b.peek(5)[0][0] == 26  # numbers are never reused, even by an empty buffer
    with FrameBuffer(tmp_path / "other.db") as other:
        assert other.stream != stream
