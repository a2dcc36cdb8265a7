"""The command delivery loop retries what may heal and stops on what will not.

A database away (locked by another process) fails rounds that are retried with backoff until
it answers again (tests/test_command_handed.py holds a lock across a send). A bug fails the
same way every round: delivery stops at once, and /readyz says so (not ready: the gateway
cannot deliver commands), instead of the loop failing every 0.1 s forever."""

from __future__ import annotations

import logging
import re
import sqlite3
from typing import Any

import pytest

from eqgw.commands import repository as q
from tests.api_helpers import Served, served, wait_for


async def _identified(s: Served) -> None:
    """Wait until SIM-001's unit is identified: until then the gateway's identifier submits
    requests, which read the pending commands too (a second caller of what a test breaks)."""
    (unit,) = s.rt.ingest.live.of_vehicle("SIM-001")

    async def identified() -> bool:
        return unit.series is not None

    await wait_for(identified, 60, "the unit identified")


@pytest.mark.parametrize(
    "failure",
    [
        pytest.param(sqlite3.OperationalError("database is locked"), id="heals"),
        pytest.param(TypeError("pending_commands() takes 2 positional arguments"), id="bug"),
    ],
)
async def test_a_failed_delivery_round_is_retried_only_when_it_may_heal(
    sqlite_url: str, monkeypatch: pytest.MonkeyPatch, failure: Exception
) -> None:
    async with served(sqlite_url, vehicles=1) as s:
        await _identified(s)
        real = q.pending_commands
        calls = 0

        def pending_commands(*args: Any, **kw: Any) -> Any:
            nonlocal calls
            calls += 1
            if calls <= 3 or isinstance(failure, TypeError):
                raise failure
            return real(*args, **kw)

        monkeypatch.setattr(q, "pending_commands", pending_commands)
        s.rt.commands.poke()  # a reload now

        async def tasks() -> dict[str, Any]:
            r = await s.client.get("/readyz", headers=s.auth())
            return {"status": r.status_code, **r.json()}

        if isinstance(failure, TypeError):

            async def stopped() -> bool:
                body = await tasks()
                return any(t["name"] == "command delivery" for t in body["tasks"])

            await wait_for(stopped, 30, "command delivery reported failed")
            body = await tasks()
            (t,) = [t for t in body["tasks"] if t["name"] == "command delivery"]
            assert t["state"] == "failed" and "TypeError" in t["last_error"], t
            assert body["status"] == 503 and body["ready"] is False, body
            assert calls == 1, "a bug was retried"
        else:

            async def recovered() -> bool:
                return calls > 3

            await wait_for(recovered, 30, "delivery rounds past the locked database")
            body = await tasks()
            assert body["status"] == 200 and body["ready"] is True, body
            assert not [t for t in body["tasks"] if t["name"] == "command delivery"], body
            # The same gateway still delivers: a command submitted now is sent.
            r = await s.client.post(
                "/api/v1/vehicles/SIM-001/commands",
                json={"jump_start_override": True},
                headers=s.auth(),
            )
            assert r.status_code == 202, r.text
            cid = r.json()["id"]

            async def sent() -> bool:
                r = await s.client.get(f"/api/v1/commands/{cid}", headers=s.auth())
                return bool(r.json()["sends"] >= 1)

            await wait_for(sent, 30, "the command sent after the failed rounds")


async def test_rounds_after_a_failure_ask_the_database_until_it_answers(
    sqlite_url: str, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    """Every retry of a failed round asks the database again: a retry that skipped it (the
    queue reloaded moments before the failure) is no sign the database is back, and the log
    says "resumed" only once it is."""
    async with served(sqlite_url, vehicles=1) as s:
        await _identified(s)
        real = q.pending_commands
        away = True
        failed = 0

        def pending_commands(*args: Any, **kw: Any) -> Any:
            nonlocal failed
            if away:
                failed += 1
                raise sqlite3.OperationalError("database is locked")
            return real(*args, **kw)

        monkeypatch.setattr(q, "pending_commands", pending_commands)
        caplog.set_level(logging.WARNING, logger="eqgw.commands.delivery")
        s.rt.commands.poke()  # a reload now, right after the last periodic one

        async def retried() -> bool:
            return failed >= 3

        # Retries after 0.5 s, 1 s and 2 s: each one a reload that fails.
        await wait_for(retried, 30, "three rounds failing on the database")
        said = [r.getMessage() for r in caplog.records]
        assert not [m for m in said if "resumed" in m], said
        assert sum("round failed" in m for m in said) == 1, said
        away = False

        async def resumed() -> bool:
            return any("resumed" in r.getMessage() for r in caplog.records)

        await wait_for(resumed, 30, "delivery resumed once the database answers")
        (line,) = [r.getMessage() for r in caplog.records if "resumed" in r.getMessage()]
        said_rounds = re.fullmatch(r"command delivery resumed after (\d+) failed rounds", line)
        assert said_rounds is not None and int(said_rounds.group(1)) >= 3, line
