"""The command queue at its edges: odd input refused with a 4xx and audited on both engines,
commands that would undo one another, and a cancel that lands while a delivery round waits."""

from __future__ import annotations

import asyncio
import time
from typing import Any

from eqgw.bus.writer import BusWriter
from tests.api_helpers import Served, served, wait_for
from tests.bus_helpers import within

V = "/api/v1/vehicles"


async def _audit(s: Served) -> list[dict[str, Any]]:
    """The refusals in the audit log, newest first (the gateway's own identification
    requests add entries of their own meanwhile, never refused ones). Refusals without a
    key are counted and written at a flush: flushed first."""
    await asyncio.to_thread(s.rt.audit_log.refusals.flush, s.rt.engine)
    r = await s.client.get("/api/v1/audit", params={"limit": 1000}, headers=s.auth())
    assert r.status_code == 200, r.text
    return [e for e in r.json()["entries"] if e["outcome"] == "refused"]


async def test_odd_input_is_refused_with_a_4xx_and_audited(db_url: str) -> None:
    async with served(db_url, vehicles=2) as s:
        viewer, op = await s.key("viewer"), s.auth(await s.key("operator"))
        json_h = {**op, "Content-Type": "application/json"}
        long_id = "A" * 65
        cases: list[tuple[str, str, dict[str, str], bytes | None, int]] = [
            # Numbers JSON cannot hold (Python's parser reads NaN, Infinity and 1e400).
            ("POST", f"{V}/SIM-002/parameters", json_h, b'{"ov_setpoint_v": NaN}', 422),
            ("POST", f"{V}/SIM-002/parameters", json_h, b'{"ov_setpoint_v": Infinity}', 422),
            ("POST", f"{V}/SIM-002/parameters", json_h, b'{"ov_setpoint_v": 1e400}', 422),
            # A NUL character, which PostgreSQL text cannot hold, in a name and in a path.
            ("POST", f"{V}/SIM-002/parameters", json_h, b'{"ov\\u0000": 29.5}', 422),
            ("POST", f"{V}/A%00B/commands", json_h, b'{"jump_start_override": true}', 422),
            # A vehicle id longer than any stored one: no key, a viewer, an operator.
            ("POST", f"{V}/{long_id}/requests", {}, b'{"what": "dm1"}', 401),
            ("POST", f"{V}/{long_id}/requests", s.auth(viewer), b'{"what": "dm1"}', 403),
            ("POST", f"{V}/{long_id}/requests", json_h, b'{"what": "dm1"}', 404),
            # A body that is not JSON at all.
            ("POST", f"{V}/SIM-001/commands", json_h, b"jump!", 400),
            ("DELETE", "/api/v1/commands/" + "x" * 300, op, None, 404),
        ]
        for method, url, headers, body, status in cases:
            before = len(await _audit(s))
            r = await s.client.request(method, url, headers=headers, content=body)
            assert r.status_code == status, (url, body, r.text)
            assert r.json()["detail"], r.text
            entries = await _audit(s)
            assert len(entries) == before + 1, (url, body, "not audited")
            assert entries[0]["status_code"] == status
        # What was stored of them: clipped, NUL and non-finite numbers made storable.
        entries = await _audit(s)
        stored = {e["vehicle_id"] for e in entries}
        assert "A\ufffdB" in stored and any(v and v.startswith("A" * 63) for v in stored)
        requests = [e["request"] for e in entries if e["request"]]
        assert {"ov_setpoint_v": "nan"} in requests and {"ov_setpoint_v": "inf"} in requests
        assert {"ov\ufffd": 29.5} in requests


async def _stop_delivery(s: Served, *vehicles: str) -> dict[str, BusWriter]:
    """Make the vehicles' buses refuse every send: their commands stay queued."""
    from eqgw.bus.reader import BusReader

    real = {}
    for v in vehicles:
        bus = f"{v}/sim"
        real[bus] = s.rt.commands.writers[bus]
        s.rt.commands.writers[bus] = BusWriter(BusReader(real[bus].reader.config))
    return real


async def test_commands_that_would_undo_a_pending_one_are_refused(db_url: str) -> None:
    async with served(db_url, vehicles=2) as s:
        op = s.auth(await s.key("operator"))
        real = await _stop_delivery(s, "SIM-001", "SIM-002")
        try:
            # Disabling CAN on/off takes equalizer on/off out of the gateway's hands.
            first = {"can_onoff_enable": True, "equalizer_on": True, "expires_in_s": 60}
            r = await s.client.post(f"{V}/SIM-001/commands", json=first, headers=op)
            assert r.status_code == 202, r.text
            off = {"can_onoff_enable": False}
            r2 = await s.client.post(f"{V}/SIM-001/commands", json=off, headers=op)
            assert r2.status_code == 409 and r2.json()["type"] == "conflict", r2.text
            assert r2.json()["command_id"] == r.json()["id"]
            assert "can_eq_onoff" in r2.json()["detail"]
            cancel = await s.client.delete(f"/api/v1/commands/{r.json()['id']}", headers=op)
            assert cancel.status_code == 200
            # ... and the other way round.
            r = await s.client.post(
                f"{V}/SIM-001/commands", json={**off, "expires_in_s": 60}, headers=op
            )
            assert r.status_code == 202, r.text
            eq = {"can_onoff_enable": True, "equalizer_on": True}
            r2 = await s.client.post(f"{V}/SIM-001/commands", json=eq, headers=op)
            assert r2.status_code == 409 and r2.json()["type"] == "conflict", r2.text
            # Unrelated control fields do not conflict with it.
            r3 = await s.client.post(
                f"{V}/SIM-001/commands", json={"jump_start_override": True}, headers=op
            )
            assert r3.status_code == 202, r3.text

            # A factory reset puts back every parameter: it conflicts with any pending write.
            w = {"ov_setpoint_v": 29.5, "expires_in_s": 60}
            r = await s.client.post(f"{V}/SIM-002/parameters", json=w, headers=op)
            assert r.status_code == 202, r.text
            reset = {"factory_reset": True}
            r2 = await s.client.post(f"{V}/SIM-002/parameters", json=reset, headers=op)
            assert r2.status_code == 409 and "factory_reset" in r2.json()["detail"], r2.text
            other = {"fault_timer_s": 12}  # another parameter: no conflict
            r3 = await s.client.post(f"{V}/SIM-002/parameters", json=other, headers=op)
            assert r3.status_code == 202, r3.text
            for cid in (r.json()["id"], r3.json()["id"]):
                cancel = await s.client.delete(f"/api/v1/commands/{cid}", headers=op)
                assert cancel.status_code == 200
            r = await s.client.post(
                f"{V}/SIM-002/parameters", json={**reset, "expires_in_s": 60}, headers=op
            )
            assert r.status_code == 202, r.text
            r2 = await s.client.post(f"{V}/SIM-002/parameters", json=other, headers=op)
            assert r2.status_code == 409 and "factory_reset" in r2.json()["detail"], r2.text
        finally:
            s.rt.commands.writers.update(real)


class _GatedWriter(BusWriter):
    """A writer whose sends wait for `gate` (a bus whose transmit path is slow)."""

    def __init__(self, real: BusWriter) -> None:
        super().__init__(real.reader)
        self.gate = asyncio.Event()
        self.waiting = asyncio.Event()

    async def send(self, can_id: int, data: bytes, **kw: Any) -> None:
        self.waiting.set()
        await self.gate.wait()
        await super().send(can_id, data, **kw)


async def test_a_command_cancelled_while_a_round_waits_is_never_sent(db_url: str) -> None:
    async with served(db_url, vehicles=2) as s:
        svc = s.rt.commands
        seen: list[int] = []
        s.sim.add_tap("SIM-002", lambda m: seen.append(m.arbitration_id))
        before = dict(s.sim.vehicle("SIM-002").unit().params)
        await svc.stop()  # both commands are pending when the next round starts
        gated = _GatedWriter(svc.writers["SIM-001/sim"])
        svc.writers["SIM-001/sim"] = gated
        r1 = await s.client.post(
            f"{V}/SIM-001/commands", json={"jump_start_override": True}, headers=s.auth()
        )
        w = {"ov_setpoint_v": 29.5, "fault_timer_s": 12}
        r2 = await s.client.post(f"{V}/SIM-002/parameters", json=w, headers=s.auth())
        assert r1.status_code == r2.status_code == 202
        svc._task = asyncio.create_task(svc._run())
        await within(gated.waiting.wait(), 10)  # the round is in SIM-001's send
        cid = r2.json()["id"]
        r = await s.client.delete(f"/api/v1/commands/{cid}", headers=s.auth())
        assert r.status_code == 200 and r.json()["state"] == "cancelled"
        gated.gate.set()
        # Two more rounds: the cancelled write's frames never reach SIM-002.
        t0 = time.monotonic()
        await wait_for(lambda: _after(t0, 2.5), what="two delivery rounds")
        assert not any((i >> 8) & 0xFFFF == 0xFFD3 for i in seen), "a cancelled write was sent"
        assert s.sim.vehicle("SIM-002").unit().params == before
        r = await s.client.get(f"/api/v1/commands/{cid}", headers=s.auth())
        assert r.json()["state"] == "cancelled" and r.json()["sends"] == 0


async def _after(t0: float, seconds: float) -> bool:
    return time.monotonic() - t0 > seconds


async def test_text_with_a_nul_character_is_refused_everywhere(db_url: str) -> None:
    """PostgreSQL text cannot hold NUL: every write with one is a 422 saying where (audited),
    on both engines alike, never a 500 from the driver."""
    async with served(db_url, vehicles=1) as s:
        nul = "a\u0000b"
        writes: list[tuple[str, str, dict[str, Any]]] = [
            ("POST", "/api/v1/keys", {"name": nul, "role": "viewer"}),
            ("POST", "/api/v1/alerts/mutes", {"duration_s": 60, "reason": nul}),
            ("POST", "/api/v1/alerts/1/acknowledge", {"comment": nul}),
            ("PATCH", "/api/v1/alerts/rules/equalizer_fault", {"description": nul}),
            ("POST", "/api/v1/webhooks", {"name": nul, "url": "http://127.0.0.1:9/h"}),
            (
                "POST",
                "/api/v1/webhooks",
                {"name": "w", "url": "http://127.0.0.1:9/h", "vehicles": ["SIM-001", nul]},
            ),
            ("POST", f"{V}/SIM-001/requests", {nul: 1, "what": "dm1"}),
        ]
        for method, url, body in writes:
            before = len(await _audit(s))
            r = await s.client.request(method, url, json=body, headers=s.auth())
            assert r.status_code == 422, (url, r.text)
            assert "NUL" in r.json()["detail"], r.text
            assert len(await _audit(s)) == before + 1, (url, "not audited")


async def test_key_names_are_checked_alike_by_the_api_and_the_cli(sqlite_url: str) -> None:
    async with served(sqlite_url, vehicles=1) as s:
        for name, word in (("   ", "empty"), ("a\nb", "control"), ("n" * 201, "200")):
            r = await s.client.post(
                "/api/v1/keys", json={"name": name, "role": "viewer"}, headers=s.auth()
            )
            assert r.status_code == 422 and word in r.json()["detail"], r.text
        r = await s.client.post(
            "/api/v1/keys", json={"name": "  depot 3 ", "role": "viewer"}, headers=s.auth()
        )
        assert r.status_code == 201 and r.json()["name"] == "depot 3", r.text


async def test_a_reload_during_a_submit_neither_sends_twice_nor_announces_out_of_order(
    sqlite_url: str,
) -> None:
    from eqgw.commands import repository as q
    from eqgw.commands.delivery import COMMAND_EVENT

    async with served(sqlite_url, vehicles=1) as s:
        svc = s.rt.commands
        events = svc.hub.subscribe(None)  # the command hub carries only command events
        db = svc._db
        queue = svc._db_serialized
        sends_meanwhile: dict[str, int] = {}

        async def racing(fn: Any, *args: Any) -> Any:
            out = await queue(fn, *args)
            if fn == svc._queue:
                # The delivery loop's reload and round, landing between the insert's commit
                # and the submit queueing the command.
                await svc._reload()
                for cmd in list(svc._pending.values()):
                    await svc._step(cmd)
                row = await db(q.get_command, args[0].id)
                assert row is not None
                sends_meanwhile[row.id] = row.sends
            return out

        svc._db_serialized = racing  # type: ignore[method-assign]
        r = await s.client.post(
            f"{V}/SIM-001/commands", json={"jump_start_override": True}, headers=s.auth()
        )
        svc._db_serialized = queue  # type: ignore[method-assign]
        assert r.status_code == 202, r.text
        cid = r.json()["id"]
        # (Other inserts, the gateway's own identification requests, may race in too.)
        assert sends_meanwhile[cid] == 0, "the command was delivered before it was queued"
        first = await within(events.get(), 10)
        while first.data["id"] != cid:  # the gateway's own identification requests
            first = await within(events.get(), 10)
        assert first.kind == COMMAND_EVENT and first.data["state"] == "queued"

        async def done() -> Any:
            got = await s.client.get(f"/api/v1/commands/{cid}", headers=s.auth())
            return got.json()["state"] == "confirmed" and got.json()

        cmd = await wait_for(done, what="the command confirmed")
        assert cmd["sends"] >= 1
        events.close()


async def test_a_command_ended_by_another_process_is_not_delivered(db_url: str) -> None:
    """An API-only instance cancels a command this gateway holds: only the row changes. The
    gateway notices at its next reload and never sends it, even once its bus is back."""
    from eqgw.commands import repository as q

    async with served(db_url, vehicles=1) as s:
        svc = s.rt.commands
        real = await _stop_delivery(s, "SIM-001")
        try:
            body = {"jump_start_override": True, "expires_in_s": 60}
            r = await s.client.post(f"{V}/SIM-001/commands", json=body, headers=s.auth())
            assert r.status_code == 202, r.text
            cid = r.json()["id"]
            with s.rt.engine.begin() as conn:
                ended = {"state": "cancelled", "reason": "elsewhere", "updated_at": time.time()}
                assert q.update_command(conn, cid, ended)

            async def dropped() -> bool:
                return cid not in svc._pending

            await wait_for(dropped, what="the gateway to drop the command")
        finally:
            svc.writers.update(real)  # the bus is back
        t0 = time.monotonic()
        await wait_for(lambda: _after(t0, 2.5), what="two delivery rounds")
        got = (await s.client.get(f"/api/v1/commands/{cid}", headers=s.auth())).json()
        assert got["state"] == "cancelled" and got["sends"] == 0
        assert s.sim.vehicle("SIM-001").unit().jso is False
