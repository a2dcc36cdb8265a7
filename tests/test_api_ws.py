"""The websocket: snapshot on subscribe, live updates, command states, slow clients dropped."""

from __future__ import annotations

import time
import warnings

import pytest
from starlette.websockets import WebSocketDisconnect

with warnings.catch_warnings():
    # Starlette wants httpx2 for its test client; httpx works and is what is installed.
    warnings.simplefilter("ignore")
    from starlette.testclient import TestClient

from app.api.settings import ApiSettings
from app.config import Settings
from app.ingest.events import LIVE, Event, UnitRef
from app.main import create_app
from app.sim.clock import RealtimeClock
from app.sim.fleet import SimulatedFleet


def _app(url: str, **api: object) -> tuple[TestClient, list[str]]:
    keys: list[str] = []
    sim = SimulatedFleet(2, seed=1, clock=RealtimeClock(4.0))
    app = create_app(
        Settings(database_url=url), api=ApiSettings(**api), sim=sim, on_first_key=keys.append
    )
    return TestClient(app), keys


def test_snapshot_then_updates_then_command_states(sqlite_url: str) -> None:
    client, keys = _app(sqlite_url)
    with client:
        deadline = time.monotonic() + 30
        while len(client.app.state.rt.ingest.live.units) < 2:  # type: ignore[attr-defined]
            assert time.monotonic() < deadline
            time.sleep(0.05)
        with client.websocket_connect(f"/api/v1/ws?key={keys[0]}&vehicles=SIM-001") as ws:
            snap = ws.receive_json()
            assert snap["type"] == "snapshot" and snap["vehicle_id"] == "SIM-001"
            assert snap["units"][0]["latest"]
            kinds = set()
            while "live" not in kinds:
                msg = ws.receive_json()
                assert msg["vehicle_id"] == "SIM-001"
                kinds.add(msg["type"])
            r = client.post(
                "/api/v1/vehicles/SIM-001/commands",
                json={"jump_start_override": True},
                headers={"Authorization": f"Bearer {keys[0]}"},
            )
            assert r.status_code == 202
            states = []
            while "confirmed" not in states:
                msg = ws.receive_json()
                if msg["type"] == "command":
                    states.append(msg["data"]["state"])
            assert states[0] == "queued" and "sending" in states


def test_no_key_is_refused(sqlite_url: str) -> None:
    client, _ = _app(sqlite_url)
    with client, client.websocket_connect("/api/v1/ws") as ws:
        assert ws.receive_json()["type"] == "error"
        with pytest.raises(WebSocketDisconnect) as exc:
            ws.receive_json()
        assert exc.value.code == 4401


def test_slow_client_is_dropped_with_a_reason(sqlite_url: str) -> None:
    client, keys = _app(sqlite_url, ws_queue=20)
    with client:
        rt = client.app.state.rt  # type: ignore[attr-defined]
        with client.websocket_connect(f"/api/v1/ws?key={keys[0]}&vehicles=SIM-002") as ws:
            assert ws.receive_json()["type"] == "snapshot"
            ref = UnitRef("SIM-002", "SIM-002/sim", 30)

            def burst() -> None:
                # Faster than any client reads: published in one go on the event loop.
                for i in range(500):
                    rt.ingest.hub.publish(Event(LIVE, ref, float(i), {"slot": "x", "fields": {}}))

            client.portal.call(burst)  # type: ignore[union-attr]
            with pytest.raises(WebSocketDisconnect) as exc:
                while True:
                    msg = ws.receive_json()
                    if msg["type"] == "error":
                        assert msg["reason"].startswith("slow consumer")
            assert exc.value.code == 1008
