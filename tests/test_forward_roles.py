"""The ingest role against a real `eqgw serve` (subprocess, SQLite): it posts frames (gzip,
duplicates, overlaps, refusals) and reads nothing; the other roles cannot post frames."""

from __future__ import annotations

import asyncio
import gzip
import json
import time
from pathlib import Path

import httpx
import pytest
import websockets

from eqgw.security.keys import ROLES, Principal, create_key
from eqgw.store.engine import create_engine
from tests.api_helpers import wait_for
from tests.bus_helpers import within
from tests.forward_helpers import VEHICLE, central_config, start_central
from tests.proc_helpers import free_port
from tests.support import web

# Frames of a minute ago: within the raw retention and not ahead of the gateway's clock.
T0 = time.time() - 60


async def test_ingest_role_posts_frames_and_nothing_else(tmp_path: Path) -> None:
    db_url = f"sqlite:///{tmp_path / 'central.db'}"
    config, ingest_key = central_config(tmp_path, db_url)
    port = free_port()
    central = await asyncio.to_thread(start_central, tmp_path, config, port)
    base = f"http://127.0.0.1:{port}/api/v1"
    body = {
        "stream": "t1",
        "vehicle": VEHICLE,
        "first_seq": 1,
        "frames": [[T0 + i, 0x18FFD61E, "d809b013ba7cc87d", 1] for i in range(5)],
    }
    try:
        async with web.AsyncClient(base_url=base, timeout=30) as c:
            engine = create_engine(db_url)
            try:
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
            assert r.json() == {
                "stream": "t1",
                "acked_seq": 5,
                "stored": 5,
                "duplicates": 0,
                "refused": 0,
                "refused_reasons": {},
            }
            r = await c.post("/ingest/frames", json=body, headers=auth(ingest_key))
            assert r.json() == {
                "stream": "t1",
                "acked_seq": 5,
                "stored": 0,
                "duplicates": 5,
                "refused": 0,
                "refused_reasons": {},
            }
            # Overlapping: only the new part is decoded.
            body2 = {**body, "first_seq": 4}
            body2["frames"] = [[T0 + 3 + i, 0x18FFD61E, "d809b013ba7cc87d", 1] for i in range(4)]
            r = await c.post("/ingest/frames", json=body2, headers=auth(ingest_key))
            assert r.json() == {
                "stream": "t1",
                "acked_seq": 7,
                "stored": 2,
                "duplicates": 2,
                "refused": 0,
                "refused_reasons": {},
            }
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

            r = await wait_for(stored, 30, "the history")
            assert len(r.json()["series"]["v12"]) == 7
        # The websocket refuses an ingest key as it refuses no key.
        async with websockets.connect(f"ws://127.0.0.1:{port}/api/v1/ws?key={ingest_key}") as ws:
            msg = json.loads(await within(ws.recv(), 10))
            assert msg["type"] == "error"
    finally:
        await asyncio.to_thread(central.stop)


@pytest.mark.parametrize("role", ROLES)
def test_ingest_stands_apart_from_the_ranked_roles(role: str) -> None:
    p = Principal(1, "k", role)
    assert p.allows("ingest") == (role == "ingest")
    assert p.allows("viewer") == (role != "ingest")
    assert p.allows("operator") == (role in ("operator", "admin"))
    assert p.allows("admin") == (role == "admin")
