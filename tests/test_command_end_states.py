"""End states tell the truth about what left the gateway: a command whose frames went to an
interface ends `unconfirmed` (it may still take effect), whatever ends it; `failed` only when
nothing left."""

from __future__ import annotations

import logging
import time
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from typing import Any

import pytest

from eqgw.bus.config import BusConfig
from eqgw.bus.reader import BusReader
from eqgw.bus.writer import BusWriter
from eqgw.commands import repository as commands_q
from tests.api_helpers import Served, served, wait_for

V = "/api/v1/vehicles"


async def _get(s: Served, cid: str) -> dict[str, Any]:
    r = await s.client.get(f"/api/v1/commands/{cid}", headers=s.auth())
    body: dict[str, Any] = r.json()
    return body


async def _submit(s: Served, expires_in_s: float) -> str:
    """Queue a jump-start override for SIM-001; its id."""
    r = await s.client.post(
        f"{V}/SIM-001/commands",
        json={"jump_start_override": True, "expires_in_s": expires_in_s},
        headers=s.auth(),
    )
    assert r.status_code == 202, r.text
    cid: str = r.json()["id"]
    return cid


async def _first_send(s: Served, cid: str) -> None:
    async def sent() -> bool:
        return (await _get(s, cid))["sends"] >= 1

    await wait_for(sent, what="a first send")


async def _end_of(s: Served, cid: str) -> dict[str, Any]:
    """The command once it has ended."""

    async def ended() -> dict[str, Any] | None:
        cmd = await _get(s, cid)
        return cmd if cmd["state"] not in ("queued", "sending") else None

    cmd: dict[str, Any] = await wait_for(ended, what="the command's end")
    return cmd


@asynccontextmanager
async def _to_nowhere(s: Served, bus: str) -> AsyncIterator[None]:
    """The bus's commands handed to an interface that takes frames and delivers them nowhere
    (no unit on its channel): sent, never confirmed. The real writer is back after."""
    commands = s.rt.commands
    real = commands.writers[bus]
    nowhere = BusReader(
        BusConfig(name=bus, vehicle_id="SIM-001", interface="virtual",
                  channel=f"nowhere-{time.monotonic_ns()}")
    )  # fmt: skip
    await nowhere.start()
    try:
        await nowhere.wait_open(15)
        commands.writers[bus] = BusWriter(nowhere)
        yield
    finally:
        commands.writers[bus] = real
        await nowhere.stop()


async def test_frames_sent_then_the_transmit_path_gone_is_unconfirmed(sqlite_url: str) -> None:
    async with served(sqlite_url, vehicles=1) as s:
        bus = "SIM-001/sim"
        async with _to_nowhere(s, bus):
            cid = await _submit(s, 60)
            await _first_send(s, cid)
            s.rt.commands.writers.pop(bus)  # the transmit path is gone for good
            cmd = await _end_of(s, cid)
            assert cmd["state"] == "unconfirmed", cmd
            assert cmd["reason"].startswith(f"no transmit path on bus '{bus}'; sent ")
            assert cmd["reason"].endswith("it may still take effect")
            events = (await s.client.get("/api/v1/audit", headers=s.auth())).json()["entries"]
            assert "command.control.unconfirmed" in [e["action"] for e in events]


async def test_nothing_sent_and_no_transmit_path_is_failed(sqlite_url: str) -> None:
    async with served(sqlite_url, vehicles=1) as s:
        bus = "SIM-001/sim"
        commands = s.rt.commands
        real = commands.writers[bus]
        # A writer whose bus never opens: every send fails before the frame is handed over.
        commands.writers[bus] = BusWriter(BusReader(real.reader.config))
        try:
            cid = await _submit(s, 60)

            async def tried() -> bool:
                return commands._tracking.get(cid) is not None and bool(
                    commands._tracking[cid].last_bus_error
                )

            await wait_for(tried, what="a send refused by the closed bus")
            commands.writers.pop(bus)
            cmd = await _end_of(s, cid)
        finally:
            commands.writers[bus] = real
        assert cmd["state"] == "failed" and cmd["sends"] == 0, cmd
        assert cmd["reason"] == f"no transmit path on bus '{bus}'"


_AUDIT_DOWN = {
    "sqlite": [
        "CREATE TRIGGER audit_down BEFORE INSERT ON audit_log "
        "BEGIN SELECT RAISE(ABORT, 'audit down'); END"
    ],
    "postgresql": [
        "CREATE FUNCTION audit_down() RETURNS trigger AS "
        "$$ BEGIN RAISE EXCEPTION 'audit down'; END $$ LANGUAGE plpgsql",
        "CREATE TRIGGER audit_down BEFORE INSERT ON audit_log "
        "FOR EACH ROW EXECUTE FUNCTION audit_down()",
    ],
}
_AUDIT_UP = {
    "sqlite": ["DROP TRIGGER audit_down"],
    "postgresql": ["DROP TRIGGER audit_down ON audit_log", "DROP FUNCTION audit_down()"],
}


async def test_an_end_state_is_never_shown_without_its_audit_entry(
    db_url: str, caplog: pytest.LogCaptureFixture
) -> None:
    """A command's end state and its audit entry commit together: while the audit log refuses
    rows, the command stays pending (the delivery retries); once it takes them, the command
    ends and its entry is there."""
    async with served(db_url, vehicles=1) as s:
        engine = s.rt.engine
        dialect = engine.dialect.name

        def run(statements: list[str]) -> None:
            with engine.begin() as conn:
                for sql in statements:
                    conn.exec_driver_sql(sql)

        def others_pending(cid: str | None = None) -> int:
            # Commands of the gateway's own (the unit's identification requests) end too, and
            # would fail on the audit log first: none may be pending while it refuses rows.
            with engine.connect() as conn:
                pending = commands_q.pending_commands(conn, ["SIM-001/sim"])
            return len([c for c in pending if c.id != cid])

        async def quiet() -> bool:
            units = s.rt.ingest.live.of_vehicle("SIM-001")
            identified = bool(units) and all(u.series is not None for u in units)
            return identified and others_pending() == 0

        await wait_for(quiet, 60, what="the unit identified, its requests ended")
        async with _to_nowhere(s, "SIM-001/sim"):
            cid = await _submit(s, 3)
            await _first_send(s, cid)
            assert others_pending(cid) == 0
            caplog.set_level(logging.ERROR, logger="eqgw.commands.delivery")
            caplog.clear()
            run(_AUDIT_DOWN[dialect])

            async def refused() -> bool:
                # A round failed on the audit log: it tried to end the command (the only one
                # pending), unanswered, out of sends or past its expiry (3 s).
                return any("audit down" in str(rec.exc_info) for rec in caplog.records)

            await wait_for(refused, what="a round ending it refused by the audit")
            assert (await _get(s, cid))["state"] in ("queued", "sending")
            run(_AUDIT_UP[dialect])
            cmd = await _end_of(s, cid)
            assert cmd["state"] == "unconfirmed", cmd
            r = await s.client.get("/api/v1/audit", headers=s.auth())
            actions = [e["action"] for e in r.json()["entries"] if e["command_id"] == cid]
            assert "command.control.unconfirmed" in actions, actions
