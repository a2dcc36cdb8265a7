"""The address claim in a running gateway (create_app, its lifespan, a simulated vehicle on a
virtual bus): claimed before the gateway's first request, and after a stronger node takes the
address, a requested DM1 is never sent and expires saying why."""

from __future__ import annotations

import asyncio

import can
import httpx

from eqgw.config import Settings
from eqgw.main import create_app
from eqgw.protocol.address_claim import claim_frame
from eqgw.sim.clock import RealtimeClock
from eqgw.sim.fleet import SimulatedFleet
from eqgw.web.settings import ApiSettings
from tests.api_helpers import lifespan, wait_for

NAME = 0x10FF_0000_0001_B3FC


async def test_a_lost_claim_stops_the_gateways_requests(db_url: str) -> None:
    sim = SimulatedFleet(1, seed=1, clock=RealtimeClock(4.0))
    keys: list[str] = []
    settings = Settings(database_url=db_url, address_claim={"name": f"0x{NAME:X}"})
    app = create_app(settings, api=ApiSettings(), sim=sim, on_first_key=keys.append)
    # The rest of the truck: a node on the same bus that sees what the gateway sends.
    truck = can.Bus(interface="virtual", channel=sim.vehicles["SIM-001"].channel)
    seen: list[can.Message] = []

    def drain() -> list[can.Message]:
        while (msg := truck.recv(0)) is not None:
            if msg.arbitration_id & 0xFF in (0xD8, 0xFE):  # the gateway's frames
                seen.append(msg)
        return seen

    try:
        async with lifespan(app):
            transport = httpx.ASGITransport(app=app)
            async with httpx.AsyncClient(transport=transport, base_url="http://test") as client:
                auth = {"Authorization": f"Bearer {keys[0]}"}

                async def identified() -> bool:
                    # The gateway's own identification requests (PGN 59904 from 0xD8).
                    return any((m.arbitration_id >> 16) & 0xFF == 0xEA for m in drain())

                await wait_for(identified, what="the gateway's first request")
                first = seen[0]
                assert (first.arbitration_id, bytes(first.data)) == claim_frame(NAME, 0xD8)
                request = next(m for m in seen if (m.arbitration_id >> 16) & 0xFF == 0xEA)
                assert request.timestamp - first.timestamp >= 0.25 - 0.01

                # A node with a lower (stronger) NAME claims 0xD8.
                stronger = claim_frame(NAME - 1, 0xD8)
                truck.send(
                    can.Message(arbitration_id=stronger[0], data=stronger[1], is_extended_id=True)
                )

                async def cannot_claim() -> bool:
                    return any(m.arbitration_id == 0x18EEFFFE for m in drain())

                await wait_for(cannot_claim, what="the gateway's 'cannot claim'")
                seen.clear()
                r = await client.post(
                    "/api/v1/vehicles/SIM-001/requests",
                    json={"what": "dm1", "expires_in_s": 2},
                    headers=auth,
                )
                assert r.status_code == 202, r.text
                command_id = r.json()["id"]

                async def ended() -> dict[str, object] | None:
                    got = await client.get(f"/api/v1/commands/{command_id}", headers=auth)
                    body: dict[str, object] = got.json()
                    return body if body["state"] not in ("queued", "sending") else None

                final = await wait_for(ended, what="the request to end")
                assert final["state"] == "expired", final
                assert "lost to NAME 0x10FF00000001B3FB" in str(final["reason"])
                await asyncio.sleep(0.2)
                assert [m for m in drain() if m.arbitration_id & 0xFF == 0xD8] == []
    finally:
        truck.shutdown()
