"""A unit that answers a command or request with a J1939 NACK or "access denied" (the
Acknowledgement PGN 59392) ends it `refused`, with its answer in the reason. The answering
node is an independent J1939 stack (can-j1939) on the simulated vehicle's bus; the gateway is
the real app on SQLite and PostgreSQL, its simulated unit deaf to commands (so nothing but the
answer can end them early)."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

import j1939

from tests.api_helpers import Served, served, wait_for

V = "/api/v1/vehicles"
VEHICLE = "SIM-001"
UNIT = 30
GW = 0xD8
PGN_ACK = 0xE800


@contextmanager
def answering_stack(channel: str, answers: dict[int, int]) -> Iterator[list[int]]:
    """An ECU of an independent J1939 stack that answers, from the unit's address, every
    frame of a PGN in `answers` (the requested PGN, for requests) sent by the gateway, with
    an Acknowledgement of control byte `answers[pgn]`. Yields the PGNs it answered."""
    ecu = j1939.ElectronicControlUnit()
    ecu.connect(interface="virtual", channel=channel)
    answered: list[int] = []

    def answer(pgn: int) -> None:
        control = answers.get(pgn)
        if control is None:
            return
        answered.append(pgn)
        ack = [control, 0xFF, 0xFF, 0xFF, GW, pgn & 0xFF, (pgn >> 8) & 0xFF, pgn >> 16]
        # PDU1 to all (J1939-21), from the unit's source address.
        ecu.send_pgn(0, PGN_ACK >> 8, 0xFF, 6, UNIT, ack)

    def on_message(priority: int, pgn: int, sa: int, timestamp: float, data: bytes) -> None:
        if sa == GW:
            answer(pgn)

    def on_request(sa: int, da: int, pgn: int) -> None:
        if sa == GW:
            answer(pgn)  # the acknowledgement names the PGN requested

    # The stack hands requests to a controller application holding the unit's address (no
    # claim of its own: the simulated unit is the one that transmits from it).
    ca = j1939.ControllerApplication(j1939.Name(value=0x1E), UNIT, bypass_address_claim=True)
    ecu.add_ca(controller_application=ca)
    ca.subscribe_request(on_request)
    ecu.subscribe(on_message, UNIT)  # frames to all and to the unit's address
    try:
        yield answered
    finally:
        ecu.disconnect()
        ecu.stop()


async def _ended(s: Served, cid: str) -> dict[str, Any]:
    async def done() -> dict[str, Any] | None:
        r = await s.client.get(f"/api/v1/commands/{cid}", headers=s.auth())
        body: dict[str, Any] = r.json()
        return body if body["state"] not in ("queued", "sending") else None

    ended: dict[str, Any] = await wait_for(done, 60, what=f"command {cid} to end")
    return ended


async def test_a_nack_or_access_denied_ends_the_command_refused(db_url: str) -> None:
    async with served(db_url, vehicles=1) as s:
        vehicle = s.sim.vehicle(VEHICLE)
        vehicle.ignore_commands(UNIT)
        op = s.auth(await s.key("operator"))
        answers = {0xFFD2: 1, 0xFFD3: 1, 0xFECA: 2}  # NACK control and parameters; DM1 denied
        with answering_stack(vehicle.channel, answers) as answered:
            r = await s.client.post(
                f"{V}/{VEHICLE}/commands", json={"jump_start_override": True}, headers=op
            )
            assert r.status_code == 202, r.text
            control = await _ended(s, r.json()["id"])
            assert control["state"] == "refused", control
            assert control["reason"] == "refused by unit 30: NACK for PGN 65490 (0xFFD2)"

            r = await s.client.post(
                f"{V}/{VEHICLE}/parameters", json={"fault_timer_s": 10}, headers=op
            )
            assert r.status_code == 202, r.text
            params = await _ended(s, r.json()["id"])
            assert params["state"] == "refused", params
            assert "NACK for PGN 65491 (0xFFD3)" in params["reason"]

            r = await s.client.post(f"{V}/{VEHICLE}/requests", json={"what": "dm1"}, headers=op)
            assert r.status_code == 202, r.text
            request = await _ended(s, r.json()["id"])
            assert request["state"] == "refused", request
            assert request["reason"] == "refused by unit 30: access denied for PGN 65226 (0xFECA)"
            assert {0xFFD2, 0xFFD3, 0xFECA} <= set(answered)

            # The unit's answer is its live state too, and the audit log says refused.
            r = await s.client.get(f"{V}/{VEHICLE}/live", headers=s.auth())
            assert r.status_code == 200, r.text
            (unit,) = [u for u in r.json()["units"] if u["sa"] == UNIT]
            ack = unit["latest"]["acknowledgement"]["fields"]
            assert ack["control"] == "access_denied" and ack["acknowledged_pgn"] == 0xFECA
