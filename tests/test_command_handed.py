"""A command whose frames were handed to an interface is never reported as unsent, whatever
fails right after the hand-over: the process dies before it records the send, the database
refuses the record, another gateway ends it, or an operator cancels it.

The failures are placed exactly where they hurt: the real BusWriter hands a real frame to the
simulated vehicle's bus (the simulated unit applies it), then the process stops dead before a
line after the send runs, or the SQLite file is write-locked by another connection. That
placement is the one part a real process cannot give deterministically (a SIGKILL lands
anywhere)."""

from __future__ import annotations

import asyncio
import sqlite3
import time
from typing import Any

import pytest

from eqgw.sim.vehicle import VehicleSpec
from tests.api_helpers import Served, served, wait_for

V = "/api/v1/vehicles"
BUS = "SIM-001/sim"
PARAMETERS_PGN = 0xFFD3
# Two parameters on two indexes (5, then 9): a write of two frames.
WRITE = {"capacity_ah": 321, "ov_setpoint_v": 29.5}


def _parameters(can_id: int) -> bool:
    return (can_id >> 8) & 0xFFFF == PARAMETERS_PGN


async def _identified(s: Served) -> None:
    """SIM-001's series is known (the gateway asked for its software ID)."""

    async def known() -> bool:
        return all(u.series == 80 for u in s.rt.ingest.live.of_vehicle("SIM-001"))

    await wait_for(known, 60, "SIM-001's series")


def _die_after_first_frame(s: Served) -> asyncio.Event:
    """The bus's writer hands the first parameters frame over for real, then the delivery
    stops dead there (cancelled only when the app stops)."""
    writer = s.rt.commands.writers[BUS]
    real = writer.send
    handed = asyncio.Event()

    async def send(can_id: int, data: bytes, **kw: Any) -> None:
        await real(can_id, data, **kw)
        if _parameters(can_id) and not handed.is_set():
            handed.set()
            await asyncio.Event().wait()

    writer.send = send  # type: ignore[method-assign]
    return handed


async def _ended(s: Served, cid: str, timeout: float = 60) -> dict[str, Any]:
    async def ended() -> dict[str, Any] | None:
        r = await s.client.get(f"/api/v1/commands/{cid}", headers=s.auth())
        cmd: dict[str, Any] = r.json()
        return cmd if cmd["state"] not in ("queued", "sending") else None

    result: dict[str, Any] = await wait_for(ended, timeout, "the command's end")
    return result


async def _first_frame_applied(s: Served) -> None:
    async def applied() -> bool:
        return bool(s.sim.vehicle("SIM-001").unit().params["capacity_ah"] == 321)

    await wait_for(applied, what="the first frame applied by the simulated unit")


@pytest.mark.parametrize("after", ["restart", "other_gateway"])
async def test_a_gateway_dead_mid_send_is_never_reported_unsent(db_url: str, after: str) -> None:
    async with served(db_url, vehicles=1) as s:
        key = s.admin_key
        await _identified(s)
        handed = _die_after_first_frame(s)
        body = {**WRITE, "expires_in_s": 3}
        r = await s.client.post(f"{V}/SIM-001/parameters", json=body, headers=s.auth())
        assert r.status_code == 202, r.text
        cid, expires_at = r.json()["id"], r.json()["expires_at"]
        async with asyncio.timeout(30):
            await handed.wait()
        await _first_frame_applied(s)
        assert s.sim.vehicle("SIM-001").unit().params["ov_setpoint_v"] != 29.5  # never sent
    # The gateway stopped dead right after the frame left. It comes back past the expiry, or
    # another gateway that does not deliver on the bus finds the command unowned.
    await asyncio.sleep(max(0.0, expires_at - time.time()) + 0.5)
    fleet: int | list[VehicleSpec] = 1 if after == "restart" else [VehicleSpec(name="OTHER-1")]
    async with served(db_url, vehicles=fleet, admin_key=key) as s2:
        cmd = await _ended(s2, cid)
    assert cmd["state"] == "unconfirmed", cmd
    assert cmd["reason"].endswith("it may still take effect"), cmd["reason"]
    assert "begun" in cmd["reason"] and "not recorded" in cmd["reason"], cmd["reason"]


async def test_the_database_refusing_the_record_of_a_send_is_never_reported_unsent(
    sqlite_url: str, caplog: pytest.LogCaptureFixture
) -> None:
    path = sqlite_url.removeprefix("sqlite:///")
    lock = sqlite3.connect(path, isolation_level=None, timeout=30)
    try:
        async with served(sqlite_url, vehicles=1) as s:
            await _identified(s)
            writer = s.rt.commands.writers[BUS]
            real = writer.send
            # The lock after the submit's own writes (its audit row): on a loaded machine the
            # first send can come before the submit has answered.
            answered = asyncio.Event()

            async def send(can_id: int, data: bytes, **kw: Any) -> None:
                await real(can_id, data, **kw)
                if _parameters(can_id) and not lock.in_transaction:
                    await answered.wait()
                    lock.execute("BEGIN IMMEDIATE")  # another process's write lock, held

            writer.send = send  # type: ignore[method-assign]
            body = {**WRITE, "expires_in_s": 3}
            r = await s.client.post(f"{V}/SIM-001/parameters", json=body, headers=s.auth())
            answered.set()
            assert r.status_code == 202, r.text
            cid, expires_at = r.json()["id"], r.json()["expires_at"]
            await _first_frame_applied(s)

            # Locked until the recording write has given up (its busy timeout: the round
            # failed) and the command is past its expiry.
            async def refused_past_expiry() -> bool:
                failed = any(
                    r.getMessage().startswith("command delivery round failed")
                    for r in caplog.records
                )
                return failed and time.time() > expires_at

            await wait_for(refused_past_expiry, 60, "the recording write refused, expired")
            lock.execute("ROLLBACK")
            cmd = await _ended(s, cid)
    finally:
        lock.close()
    assert cmd["state"] == "unconfirmed", cmd
    assert cmd["reason"].endswith("it may still take effect"), cmd["reason"]


async def test_a_command_cancelled_after_a_send_says_what_was_sent(db_url: str) -> None:
    async with served(db_url, vehicles=1, resend_interval_s=60) as s:
        await _identified(s)
        r = await s.client.post(f"{V}/SIM-001/parameters", json=WRITE, headers=s.auth())
        assert r.status_code == 202, r.text
        cid = r.json()["id"]

        async def sent() -> bool:
            r = await s.client.get(f"/api/v1/commands/{cid}", headers=s.auth())
            return bool(r.json()["sends"] >= 1)

        await wait_for(sent, what="a first send")
        r = await s.client.delete(f"/api/v1/commands/{cid}", headers=s.auth())
        assert r.status_code == 200, r.text
        cmd = r.json()
    assert cmd["state"] == "cancelled"
    assert cmd["reason"].startswith("cancelled by ") and "after it was sent 1 time" in cmd["reason"]
    assert cmd["reason"].endswith("what was sent may still take effect"), cmd["reason"]


async def test_a_round_due_after_another_process_cancelled_hands_nothing_over(
    db_url: str,
) -> None:
    """Another process cancels (only the row changes); the next resend comes due before this
    gateway's reload would notice. The round's write-ahead finds the command ended: no frame."""
    from eqgw.commands import repository as q

    async with served(db_url, vehicles=1, resend_interval_s=60, parameter_sends=60) as s:
        await _identified(s)
        svc = s.rt.commands
        frames: list[int] = []
        s.sim.add_tap(
            "SIM-001",
            lambda m: frames.append(m.arbitration_id) if _parameters(m.arbitration_id) else None,
        )
        r = await s.client.post(f"{V}/SIM-001/parameters", json=WRITE, headers=s.auth())
        assert r.status_code == 202, r.text
        cid = r.json()["id"]

        async def sent() -> bool:
            return bool(len(frames) >= 2 and cid in svc._pending and svc._pending[cid].sends == 1)

        await wait_for(sent, what="a first send of both frames")

        async def no_reload() -> None:
            return None  # the reload that would notice the cancel is not due yet

        svc._reload = no_reload  # type: ignore[method-assign]
        with s.rt.engine.begin() as conn:
            ended = {
                "state": "cancelled",
                "reason": "by another process",
                "updated_at": time.time(),
            }
            assert q.update_command(conn, cid, ended)
        before = len(frames)
        svc._pending[cid].last_sent_at = 0.0  # the resend is due now
        svc._tracking[cid].last_attempt = 0.0
        svc.poke()

        async def dropped() -> bool:
            return cid not in svc._pending

        await wait_for(dropped, what="the round to find the command ended")
        await asyncio.sleep(0.5)
        assert len(frames) == before, "a frame was handed over after the cancel"
