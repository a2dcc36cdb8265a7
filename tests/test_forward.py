"""Edge forwarding: the central service down for minutes of simulated time and back, every
frame stored once; the buffer bound; the ingest role. Central: `eqgw serve` in a subprocess on
SQLite and PostgreSQL; forwarder: in-process, reading a simulated vehicle's virtual bus."""

from __future__ import annotations

import asyncio
import gzip
import json
from pathlib import Path

import httpx
import pytest

from app.bus.config import BusConfig
from app.forward.buffer import FrameBuffer
from app.forward.uploader import Forwarder, UploadSettings
from app.store.engine import create_engine
from tests.forward_helpers import (
    VEHICLE,
    Process,
    RecordedVehicle,
    async_wait,
    async_wait_async,
    central_config,
    free_port,
    replay_counts,
    start_central,
    stream_row,
    table_counts,
)


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
    veh = RecordedVehicle()
    buffer = FrameBuffer(tmp_path / "fwd.db")
    engine = create_engine(db_url)
    fwd = _forwarder(veh, buffer, port, key)
    central: Process | None = None
    try:
        await fwd.start()
        await fwd.reader.wait_open(10)
        veh.fleet.open()
        # Ten minutes of driving while the central service is unreachable.
        await _run_sim(veh, fwd, 600)
        n1 = len(veh.kept())
        assert n1 > 1000
        await async_wait(lambda: fwd.uploader.status().consecutive_failures >= 2, 30, "retries")
        assert buffer.status().rows == n1 and buffer.status().acked_seq == 0
        # Back: the backlog goes up in batches.
        central = await _start_central(tmp_path, config, port)
        await async_wait(lambda: buffer.status().acked_seq == n1, 60, "the backlog uploaded")
        assert buffer.status().rows == 0
        # Two more minutes online, then the central dies (SIGKILL) for three minutes.
        await _run_sim(veh, fwd, 120)
        central.kill()
        central = None
        await _run_sim(veh, fwd, 180)
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
    want = replay_counts(veh.sent, tmp_path)
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
    assert table_counts(db_url) == replay_counts(kept[-300:], tmp_path)


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


async def test_ingest_role_posts_frames_and_nothing_else(tmp_path: Path) -> None:
    db_url = f"sqlite:///{tmp_path / 'central.db'}"
    config, ingest_key = central_config(tmp_path, db_url)
    port = free_port()
    central = await _start_central(tmp_path, config, port)
    base = f"http://127.0.0.1:{port}/api/v1"
    body = {
        "stream": "t1",
        "vehicle": VEHICLE,
        "first_seq": 1,
        "frames": [[1.7e9 + i, 0x18FFD61E, "d809b013ba7cc87d", 1] for i in range(5)],
    }
    try:
        async with httpx.AsyncClient(base_url=base, timeout=30) as c:
            from tests.forward_helpers import create_engine as ce

            engine = ce(db_url)
            try:
                from app.api.auth import create_key

                keys = {r: create_key(engine, r, r)[1] for r in ("viewer", "operator", "admin")}
            finally:
                engine.dispose()

            def auth(k: str) -> dict[str, str]:
                return {"Authorization": f"Bearer {k}"}

            for role, k in keys.items():
                r = await c.post("/ingest/frames", json=body, headers=auth(k))
                assert r.status_code == 403, (role, r.text)
                r = await c.get("/vehicles", headers=auth(k))
                assert r.status_code == 200
            for path in ("/vehicles", f"/vehicles/{VEHICLE}/live", "/faults", "/me", "/keys"):
                r = await c.get(path, headers=auth(ingest_key))
                assert r.status_code == 403, (path, r.text)
            r = await c.post(
                "/keys", json={"name": "x", "role": "viewer"}, headers=auth(ingest_key)
            )
            assert r.status_code == 403
            # Gzip, then the same batch again: stored once, answered as duplicates.
            gz = gzip.compress(json.dumps(body).encode())
            headers = {**auth(ingest_key), "Content-Encoding": "gzip"}
            headers["Content-Type"] = "application/json"
            r = await c.post("/ingest/frames", content=gz, headers=headers)
            assert r.json() == {"stream": "t1", "acked_seq": 5, "stored": 5, "duplicates": 0}
            r = await c.post("/ingest/frames", json=body, headers=auth(ingest_key))
            assert r.json() == {"stream": "t1", "acked_seq": 5, "stored": 0, "duplicates": 5}
            # Overlapping: only the new part is decoded.
            body2 = {**body, "first_seq": 4}
            body2["frames"] = [[1.7e9 + 3 + i, 0x18FFD61E, "d809b013ba7cc87d", 1] for i in range(4)]
            r = await c.post("/ingest/frames", json=body2, headers=auth(ingest_key))
            assert r.json() == {"stream": "t1", "acked_seq": 7, "stored": 2, "duplicates": 2}
            # Refusals: unknown vehicle, a bus of another vehicle, a stream moving vehicles.
            r = await c.post(
                "/ingest/frames", json={**body, "vehicle": "NOPE"}, headers=auth(ingest_key)
            )
            assert r.status_code == 404
            r = await c.post(
                "/ingest/frames", json={**body, "bus": "OTHER/can0"}, headers=auth(ingest_key)
            )
            assert r.status_code == 422
            r = await c.post(
                "/ingest/frames", json={**body, "bus": f"{VEHICLE}/can1"}, headers=auth(ingest_key)
            )
            assert r.status_code == 409
            r = await c.post("/ingest/frames", content=b"not gzip", headers=headers)
            assert r.status_code == 400
            # Readable by a viewer (the fleet listing is cached briefly: poll).
            history = f"/vehicles/{VEHICLE}/history?from=0&to=2e9&bucket=raw"

            async def stored() -> httpx.Response | None:
                r = await c.get(history, headers=auth(keys["viewer"]))
                return r if r.status_code == 200 else None

            r = await async_wait_async(stored, 30, "the history")
            assert len(r.json()["series"]["v12"]) == 7
        # The websocket refuses an ingest key as it refuses no key.
        import websockets

        async with websockets.connect(f"ws://127.0.0.1:{port}/api/v1/ws?key={ingest_key}") as ws:
            msg = json.loads(await asyncio.wait_for(ws.recv(), 10))
            assert msg["type"] == "error"
    finally:
        await asyncio.to_thread(central.stop)


@pytest.mark.parametrize("role", ["viewer", "operator", "admin", "ingest"])
def test_ingest_stands_apart_from_the_ranked_roles(role: str) -> None:
    from app.api.auth import ROLES, Principal

    assert role in ROLES
    p = Principal(1, "k", role)
    assert p.allows("ingest") == (role == "ingest")
    assert p.allows("viewer") == (role != "ingest")
    assert p.allows("admin") == (role == "admin")
