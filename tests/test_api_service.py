"""The service end to end: httpx against the real app, the simulator, SQLite and PostgreSQL."""

from __future__ import annotations

import re
import time
import uuid
from collections.abc import AsyncIterator
from typing import Any

import orjson
import pytest
import pytest_asyncio

from eqgw.api.ws import _snapshots
from eqgw.bus.reader import BusReader
from eqgw.bus.writer import BusWriter
from eqgw.security.keys import Scope
from tests.api_helpers import Served, served, wait_for

V = "/api/v1/vehicles"


async def _command(s: Served, cid: str, states: tuple[str, ...]) -> dict[str, Any]:
    async def done() -> dict[str, Any] | None:
        r = await s.client.get(f"/api/v1/commands/{cid}", headers=s.auth())
        body: dict[str, Any] = r.json()
        return body if body["state"] in states else None

    result: dict[str, Any] = await wait_for(done, what=f"command in {states}")
    return result


async def test_roles_keys_and_reads(db_url: str) -> None:
    async with served(db_url) as s:
        c = s.client
        assert (await c.get(V)).status_code == 401
        r = await c.get(V, headers={"Authorization": "Bearer nope"})
        assert r.status_code == 401 and r.json()["type"] == "unauthorized"
        viewer = await s.key("viewer")
        operator = await s.key("operator", "depot 3")
        # Viewers read; they cannot write or manage keys.
        r = await c.get(V, headers=s.auth(viewer))
        assert r.status_code == 200
        fleet = {v["id"]: v for v in r.json()["vehicles"]}
        assert set(fleet) == {"SIM-001", "SIM-002", "SIM-003"}
        unit = fleet["SIM-001"]["units"][0]
        assert unit["online"] and unit["v12"] > 10 and unit["imbalance_v"] is not None
        r = await c.post(
            f"{V}/SIM-001/commands", json={"equalizer_on": True}, headers=s.auth(viewer)
        )
        assert r.status_code == 403 and r.json()["type"] == "forbidden"
        r = await c.post(
            "/api/v1/keys", json={"name": "x", "role": "admin"}, headers=s.auth(operator)
        )
        assert r.status_code == 403
        # Live: every latest value, status flags and the diagnosis with its numbers.
        r = await c.get(f"{V}/SIM-003/live", headers=s.auth(viewer))
        live = r.json()
        assert [u["unit"] for u in live["units"]] == [30, 31]
        d = live["units"][0]["diagnosis"]
        assert d["condition"] in ("standby", "normal", "overload", "equalizer_not_functioning",
                                  "abnormal", "shutdown_risk")  # fmt: skip
        assert d["battery_a_v"] is not None and d["b_minus_a_v"] is not None
        assert live["units"][0]["status_flags"]["eqrn"] in ("active", "inactive")
        assert (await c.get(f"{V}/NOPE/live", headers=s.auth(viewer))).status_code == 404

        # History, JSON and CSV, once the writer has stored some rows.
        async def history() -> Any:
            r = await c.get(f"{V}/SIM-001/history?bucket=raw&fields=v12,v24", headers=s.auth())
            return r.status_code == 200 and r.json()["series"]["v12"] and r.json()

        h = await wait_for(history, what="stored measurements")
        assert h["bucket"] == "raw" and h["series"]["v24"]
        r = await c.get(
            f"{V}/SIM-001/history?bucket=raw", headers={**s.auth(), "Accept": "text/csv"}
        )
        assert r.headers["content-type"].startswith("text/csv")
        assert r.text.splitlines()[0] == "ts,field,value"
        r = await c.get(f"{V}/SIM-001/history?bucket=1m&format=csv", headers=s.auth())
        assert r.text.splitlines()[0] == "ts,field,count,min,max,avg"
        r = await c.get(f"{V}/SIM-001/history?fields=bogus", headers=s.auth())
        assert r.status_code == 422 and r.json()["type"] == "invalid_fields"
        # Faults: an injected overload makes an imbalance; the lists answer either way.
        r = await c.get("/api/v1/faults?active=true", headers=s.auth(viewer))
        assert r.status_code == 200 and "episodes" in r.json()
        r = await c.get(f"{V}/SIM-001/faults?code=IMB", headers=s.auth(viewer))
        assert r.status_code == 200
        # Revocation takes effect at once in this process.
        keys = (await c.get("/api/v1/keys", headers=s.auth())).json()
        vid = next(k["id"] for k in keys if k["role"] == "viewer")
        assert (await c.delete(f"/api/v1/keys/{vid}", headers=s.auth())).status_code == 200
        assert (await c.get(V, headers=s.auth(viewer))).status_code == 401
        # Health, readiness, metrics.
        assert (await c.get("/healthz")).json() == {"status": "ok"}
        assert (await c.get("/readyz")).json()["ready"] is True
        m = (await c.get("/metrics", headers=s.auth())).text
        assert "eqgw_frames_total" in m and "eqgw_api_request_seconds" in m
        lag = re.search(r"^eqgw_writer_lag_seconds (\S+)$", m, re.M)
        assert lag is not None and 0 <= float(lag.group(1)) < 60
        # Latency is labelled by route template (what bench/api.py reads), not by raw path.
        hist = r'^eqgw_api_request_seconds_count\{method="GET",route="([^"]+)",status="200"\}'
        routes = set(re.findall(hist, m, re.M))
        assert {"/api/v1/vehicles", "/api/v1/vehicles/{vehicle_id}/history"} <= routes, routes
        assert not any("SIM-001" in r for r in routes), routes
        # The event-loop lag probe has been running since startup (a sample every 100 ms).
        probes = re.search(r"^eqgw_event_loop_lag_seconds_count (\S+)$", m, re.M)
        assert probes is not None and float(probes.group(1)) > 0
        # The refused write is in the audit log.
        audit = (await c.get("/api/v1/audit", headers=s.auth(operator))).json()["entries"]
        assert any(e["outcome"] == "refused" and e["status_code"] == 403 for e in audit)


async def test_control_confirmed_parameters_sent_request_answered(db_url: str) -> None:
    async with served(db_url) as s:
        c = s.client
        op = s.auth(await s.key("operator"))
        r = await c.post(f"{V}/SIM-001/commands", json={"jump_start_override": True}, headers=op)
        assert r.status_code == 202, r.text
        cmd = await _command(s, r.json()["id"], ("confirmed", "failed", "expired"))
        assert cmd["state"] == "confirmed", cmd
        assert s.sim.vehicle("SIM-001").unit().jso is True
        # Equalizer off needs CAN on/off: refused alone, accepted when the command enables it.
        r = await c.post(f"{V}/SIM-001/commands", json={"equalizer_on": False}, headers=op)
        assert r.status_code == 409 and r.json()["type"] == "onoff_not_enabled"
        body = {"can_onoff_enable": True, "equalizer_on": False}
        r = await c.post(f"{V}/SIM-001/commands", json=body, headers=op)
        assert r.status_code == 202
        # A second conflicting command while the first is pending.
        r2 = await c.post(f"{V}/SIM-001/commands", json={"can_onoff_enable": True}, headers=op)
        assert r2.status_code == 409 and r2.json()["type"] == "conflict"
        cmd = await _command(s, r.json()["id"], ("confirmed", "failed", "expired"))
        assert cmd["state"] == "confirmed" and not s.sim.vehicle("SIM-001").unit().commanded_on
        # Parameter write: the simulator's thresholds change; no read-back, so "sent".
        r = await c.post(
            f"{V}/SIM-002/parameters", json={"ov_setpoint_v": 29.5, "fault_timer_s": 12}, headers=op
        )
        assert r.status_code == 202, r.text
        cmd = await _command(s, r.json()["id"], ("sent", "failed", "expired"))
        assert cmd["state"] == "sent" and "not confirmable" in cmd["reason"]
        params = s.sim.vehicle("SIM-002").unit().params
        assert params["ov_setpoint_v"] == 29.5 and params["fault_timer_s"] == 12
        # Requests are confirmed by the answer.
        r = await c.post(f"{V}/SIM-001/requests", json={"what": "software_id"}, headers=op)
        cmd = await _command(s, r.json()["id"], ("confirmed", "failed", "expired"))
        assert cmd["state"] == "confirmed"
        listed = [
            cmd
            for cmd in (await c.get("/api/v1/commands?vehicle=SIM-001", headers=op)).json()
            if cmd["key_name"] != "eqgw (identification)"  # the gateway's own requests
        ]
        assert len(listed) == 3


@pytest_asyncio.fixture(scope="module", loop_scope="module")
async def refusing(tmp_path_factory: pytest.TempPathFactory) -> AsyncIterator[Served]:
    """One gateway for the refusal cases: a refused request changes nothing but the audit, and
    each case reads the entries of a key of its own."""
    async with served(f"sqlite:///{tmp_path_factory.mktemp('refusals') / 'eqgw.db'}") as s:
        yield s


@pytest.mark.asyncio(loop_scope="module")
@pytest.mark.parametrize(
    ("path", "body", "status", "type_"),
    [
        ("NOPE/commands", {"equalizer_on": True}, 404, "unknown_vehicle"),
        ("SIM-001/commands", {"unit": 99, "jump_start_override": True}, 404, "unknown_unit"),
        ("SIM-003/commands", {"jump_start_override": True}, 422, "all_units_required"),
        ("SIM-003/parameters", {"unit": 31, "ov_setpoint_v": 35.0}, 422, "all_units_required"),
        ("SIM-003/requests", {"what": "dm1"}, 422, "unit_required"),
        ("SIM-001/commands", {}, 422, "empty_command"),
        ("SIM-001/commands", {"smart_sensor_messages": False}, 422, "unsupported_field"),
        ("SIM-001/commands", {"bogus": True}, 422, "validation_error"),
        ("SIM-001/parameters", {"ov_setpoint_v": 45.0}, 422, "invalid_parameters"),
        ("SIM-002/parameters", {"capacity_ah": 100}, 422, "unsupported_field"),
        ("SIM-001/requests", {"what": "nonsense"}, 422, "validation_error"),
        # true/false only: lax parsing would make 1 or "off" a command nobody meant.
        ("SIM-001/commands", {"jump_start_override": 1}, 422, "validation_error"),
        ("SIM-001/commands", {"equalizer_on": "off"}, 422, "validation_error"),
        ("SIM-001/commands", {"unit": True, "jump_start_override": True}, 422, "validation_error"),
    ],
)
async def test_refusals_are_clear_and_audited(
    refusing: Served, path: str, body: dict[str, Any], status: int, type_: str
) -> None:
    s = refusing
    name = f"operator-{uuid.uuid4().hex[:8]}"
    op = s.auth(await s.key("operator", name))
    r = await s.client.post(f"{V}/{path}", json=body, headers=op)
    assert r.status_code == status, r.text
    assert r.json()["type"] == type_ and r.json()["detail"]
    # Every refusal is audited, those of a body failing validation included.
    audit = (await s.client.get("/api/v1/audit", headers=op)).json()["entries"]
    audit = [e for e in audit if e["key_name"] == name]  # this case's only
    assert len(audit) == 1, audit
    assert audit[0]["outcome"] == "refused" and audit[0]["status_code"] == status
    assert audit[0]["vehicle_id"] == path.split("/")[0]


async def test_offline_unit_refused(sqlite_url: str) -> None:
    # The unit's wiring is cut for real while the engine's frames go on: it goes OFFLINE by
    # the monitor, not by a fault written into the live state (a frame arriving meanwhile
    # closed such a fake). The window is longer than the unit's longest gap between frames
    # (status every 3 s, DM1 every 1 s): at 1 s, the DM1 period, a loaded machine opened a
    # true-to-config OFFLINE before the cut that the unit's next frame closed.
    monitor = {"offline_after_s": 3.5}
    async with served(sqlite_url, config={"monitor": monitor}, background_traffic=True) as s:
        st = s.rt.ingest.live.of_vehicle("SIM-001")[0]
        s.sim.disconnect_unit("SIM-001")

        async def offline() -> bool:
            return "OFFLINE" in st.faults.open

        await wait_for(offline, what="SIM-001 offline")
        r = await s.client.post(f"{V}/SIM-001/commands", json={"jump_start_override": True},
                                headers=s.auth())  # fmt: skip
        assert r.status_code == 409 and r.json()["type"] == "unit_offline"
        assert "offline" in r.json()["detail"]
        s.sim.reconnect_unit("SIM-001")

        async def online() -> bool:
            return "OFFLINE" not in st.faults.open

        await wait_for(online, what="SIM-001 back online")
        r = await s.client.post(f"{V}/SIM-001/commands", json={"jump_start_override": True},
                                headers=s.auth())  # fmt: skip
        assert r.status_code == 202, r.text


async def test_parked_vehicle_refused_then_accepted_once_switched_on(sqlite_url: str) -> None:
    # Ignition off: the whole bus is silent. The vehicle is parked (no OFFLINE episode) and a
    # command is refused as nothing would hear it; the listing, the live view and the
    # websocket snapshot say parked, with when it was last heard.
    monitor = {"offline_after_s": 5.0, "bus_silent_after_s": 4.0}
    async with served(sqlite_url, config={"monitor": monitor}, background_traffic=True) as s:
        st = s.rt.ingest.live.of_vehicle("SIM-001")[0]
        s.sim.ignition_off("SIM-001")

        async def parked() -> bool:
            return st.state() == "parked"

        await wait_for(parked, what="SIM-001 parked")
        assert "OFFLINE" not in st.faults.open
        r = await s.client.post(f"{V}/SIM-001/commands", json={"jump_start_override": True},
                                headers=s.auth())  # fmt: skip
        assert r.status_code == 409 and "parked" in r.json()["detail"], r.text
        listing = (await s.client.get(V, headers=s.auth())).json()["vehicles"]
        v = {x["id"]: x for x in listing}
        assert v["SIM-001"]["state"] == "parked" and v["SIM-002"]["state"] == "ok"
        assert v["SIM-001"]["parked_since"] == st.faults.parked_since
        assert v["SIM-001"]["last_heard"] == st.last_seen
        assert v["SIM-001"]["units"][0]["state"] == "parked"
        live = (await s.client.get(f"{V}/SIM-001/live", headers=s.auth())).json()
        assert live["state"] == "parked" and live["units"][0]["state"] == "parked"
        (snap,) = _snapshots(s.rt, {"SIM-001"}, Scope())
        assert orjson.loads(snap.body)["vehicle"]["state"] == "parked"
        s.sim.ignition_on("SIM-001")

        async def back() -> bool:
            return st.state() == "online"

        await wait_for(back, what="SIM-001 heard again")
        r = await s.client.post(f"{V}/SIM-001/commands", json={"jump_start_override": True},
                                headers=s.auth())  # fmt: skip
        assert r.status_code == 202, r.text
        assert not [f for f in st.faults.open if f == "OFFLINE"]


async def test_idempotency_and_rate_limit(sqlite_url: str) -> None:
    async with served(sqlite_url, write_rate=3) as s:
        op = s.auth(await s.key("operator"))
        h = {**op, "Idempotency-Key": "abc-1"}
        r1 = await s.client.post(f"{V}/SIM-001/requests", json={"what": "dm1"}, headers=h)
        r2 = await s.client.post(f"{V}/SIM-001/requests", json={"what": "dm1"}, headers=h)
        assert r1.status_code == r2.status_code == 202 and r1.json()["id"] == r2.json()["id"]
        r3 = await s.client.post(f"{V}/SIM-001/requests", json={"what": "software_id"}, headers=h)
        assert r3.status_code == 422 and r3.json()["type"] == "idempotency_key_reused"

        # The gateway's own identification requests to SIM-002 must be over first: a
        # component_id request of ours would conflict with one still sending (a 409).
        async def identified() -> bool:
            r = await s.client.get("/api/v1/commands?vehicle=SIM-002", headers=op)
            units = s.rt.ingest.live.of_vehicle("SIM-002")
            return (
                bool(units)
                and all(u.series for u in units)
                and not any(c["state"] in ("queued", "sending") for c in r.json())
            )

        await wait_for(identified, 60, "SIM-002 identified, its requests ended")
        # Neither the replay nor the reused key's refusal counted against the limit (3).
        for what in ("dm1", "component_id"):
            r = await s.client.post(f"{V}/SIM-002/requests", json={"what": what}, headers=op)
            assert r.status_code == 202, r.text
        r4 = await s.client.post(f"{V}/SIM-002/requests", json={"what": "software_id"}, headers=op)
        assert r4.status_code == 429 and "Retry-After" in r4.headers
        # Past the limit, a retry of a command already made still gets that command.
        r5 = await s.client.post(f"{V}/SIM-001/requests", json={"what": "dm1"}, headers=h)
        assert r5.status_code == 202 and r5.json()["id"] == r1.json()["id"]
        # Cancelling is a write too.
        r6 = await s.client.delete(f"/api/v1/commands/{r1.json()['id']}", headers=op)
        assert r6.status_code == 429


async def test_every_write_endpoint_shares_the_rate_limit_with_retry_after(sqlite_url: str) -> None:
    async with served(sqlite_url, write_rate=2) as s:
        admin = s.auth()
        ok = await s.client.post(
            "/api/v1/keys", json={"name": "a", "role": "viewer"}, headers=admin
        )
        assert ok.status_code == 201, ok.text
        hook = {"name": "ops", "url": "http://receiver.invalid/hook"}
        ok = await s.client.post("/api/v1/webhooks", json=hook, headers=admin)
        assert ok.status_code == 201, ok.text
        # The key's two writes are spent: keys, webhooks and commands all refuse alike.
        for path, body in (
            ("/api/v1/keys", {"name": "b", "role": "viewer"}),
            ("/api/v1/webhooks", {**hook, "name": "ops2"}),
            (f"{V}/SIM-001/requests", {"what": "dm1"}),
        ):
            r = await s.client.post(path, json=body, headers=admin)
            assert r.status_code == 429, (path, r.text)
            assert int(r.headers["Retry-After"]) >= 1
            assert r.json()["type"] == "rate_limited"
        entries = (await s.client.get("/api/v1/audit", headers=admin)).json()["entries"]
        refused = [e for e in entries if e["status_code"] == 429]
        assert len(refused) == 3 and all(e["outcome"] == "refused" for e in refused)


async def test_command_expires_while_bus_down_and_is_never_sent(sqlite_url: str) -> None:
    async with served(sqlite_url) as s:
        bus = "SIM-001/sim"
        # Control frames (PGN 65490) only: the gateway's own identification requests go out on
        # this bus too, whenever a unit comes online, and are none of this command's business.
        control: list[int] = []
        s.sim.add_tap(
            "SIM-001",
            lambda m: (
                control.append(m.arbitration_id)
                if (m.arbitration_id >> 8) & 0xFFFF == 0xFFD2
                else None
            ),
        )
        real = s.rt.commands.writers[bus]
        # A writer whose bus is not open: every send fails with BusNotOpenError.
        down = BusReader(real.reader.config)
        s.rt.commands.writers[bus] = BusWriter(down)
        try:
            r = await s.client.post(
                f"{V}/SIM-001/commands",
                json={"jump_start_override": True, "expires_in_s": 1.5},
                headers=s.auth(),
            )
            assert r.status_code == 202
            cmd = await _command(s, r.json()["id"], ("expired", "confirmed", "failed"))
            assert cmd["state"] == "expired" and cmd["sends"] == 0
            assert "before it could be sent" in cmd["reason"]
        finally:
            s.rt.commands.writers[bus] = real  # the bus is back
        t0 = time.monotonic()
        await wait_for(lambda: _after(t0, 2.5), what="two delivery rounds")
        assert control == []  # no control frame, ever
        assert s.sim.vehicle("SIM-001").unit().jso is False


async def _after(t0: float, seconds: float) -> bool:
    return time.monotonic() - t0 > seconds


async def test_a_command_for_a_bus_nobody_delivers_on_still_expires(db_url: str) -> None:
    from eqgw.commands import repository as api_queries
    from eqgw.commands.model import Command

    async with served(db_url) as s:
        now = time.time()
        row = {
            "id": "0b7c1d2e-0000-4000-8000-000000000001", "kind": "control",
            "vehicle_id": "SIM-001", "bus": "SIM-001/gone", "sa": 30,
            "payload": {"fields": {"can_jso": "enable"}}, "state": "queued", "reason": None,
            "created_at": now - 60, "updated_at": now - 60, "expires_at": now - 30,
            "first_sent_at": None, "last_sent_at": None, "sends": 0, "max_sends": 3,
            "key_id": None, "key_name": "another gateway", "idempotency_key": None,
        }  # fmt: skip
        # Queued by a gateway that has gone, for a bus no running gateway reads.
        with s.rt.engine.begin() as conn:
            api_queries.insert_command(conn, Command.from_row(row))
            api_queries.insert_command(
                conn, Command.from_row({**row, "id": row["id"][:-1] + "2", "expires_at": now + 600})
            )

        async def state(cid: str) -> str:
            r = await s.client.get(f"/api/v1/commands/{cid}", headers=s.auth())
            assert r.status_code == 200, r.text
            return str(r.json()["state"])

        async def expired() -> bool:
            return await state(row["id"]) == "expired"

        await wait_for(expired, what="the stale command to expire")
        r = await s.client.get(f"/api/v1/commands/{row['id']}", headers=s.auth())
        assert "no gateway delivered on SIM-001/gone" in r.json()["reason"]
        assert r.json()["sends"] == 0
        assert await state(row["id"][:-1] + "2") == "queued"  # not yet expired: left alone
        audit = (await s.client.get("/api/v1/audit", headers=s.auth())).json()["entries"]
        assert [e["outcome"] for e in audit if e["command_id"] == row["id"]] == ["expired"]


async def test_readyz_counts_a_writer_the_database_refuses(
    sqlite_url: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Reads answer, writes do not (another process holds the SQLite write lock): not ready,
    saying why; ready again once the writer's rows are in."""
    import sqlite3

    import eqgw.store.engine as store_engine

    async with served(sqlite_url, vehicles=1) as s:
        # Writes blocked by the other process fail after half a second, not ten: set once the
        # gateway has started (its start writes from several threads, and on a loaded machine
        # one of them waited out a 500 ms timeout for another's transaction: the start
        # failed), on the connections opened from now on.
        monkeypatch.setattr(store_engine, "SQLITE_BUSY_TIMEOUT_MS", 500)
        s.rt.engine.dispose()
        path = sqlite_url.removeprefix("sqlite:///")
        blocker = sqlite3.connect(path, isolation_level=None)
        try:
            blocker.execute("BEGIN IMMEDIATE")

            async def refused() -> Any:
                r = await s.client.get("/readyz", headers=s.auth())
                return r.status_code == 503 and r.json()

            body = await wait_for(refused, what="readiness lost while writes fail")
            assert body["database"]["error"].startswith("writes failing"), body
            assert body["database"]["writer"]["pending_rows"] > 0
        finally:
            blocker.execute("ROLLBACK")
            blocker.close()

        async def ready() -> bool:
            return (await s.client.get("/readyz")).status_code == 200

        await wait_for(ready, what="ready again")
