"""In a running gateway (the app, its lifespan, a simulated vehicle, SQLite and PostgreSQL):
two nodes of an independent J1939 stack (can-j1939) contend for the equalizer's address 30; the
unit shows the NAME that holds it, the change of owner is reported on the unit and stored, and
the old node's live values are gone."""

from __future__ import annotations

import time
from collections.abc import Iterator
from typing import Any

import j1939
import pytest

from tests.api_helpers import Served, served, wait_for
from tests.db_helpers import query
from tests.j1939_helpers import stack_name

VEHICLE = "SIM-001"
UNIT = 30


@pytest.fixture
def names() -> tuple[j1939.Name, j1939.Name]:
    return stack_name(1, 130, 7), stack_name(0, 0, 3)  # the second is lower: it wins


@pytest.fixture
def stack() -> Iterator[list[j1939.ElectronicControlUnit]]:
    ecus: list[j1939.ElectronicControlUnit] = []
    yield ecus
    for ecu in ecus:
        ecu.disconnect()
        ecu.stop()


def _claim_from(
    stack: list[j1939.ElectronicControlUnit], channel: str, name: j1939.Name
) -> j1939.ControllerApplication:
    ecu = j1939.ElectronicControlUnit()
    ecu.connect(interface="virtual", channel=channel)
    stack.append(ecu)
    ca = j1939.ControllerApplication(name, UNIT)
    ecu.add_ca(controller_application=ca)
    ca.start()
    return ca


async def _claim_value(s: Served) -> dict[str, Any] | None:
    r = await s.client.get(f"/api/v1/vehicles/{VEHICLE}/live", headers=s.auth())
    (unit,) = [u for u in r.json()["units"] if u["sa"] == UNIT]
    claim = unit["latest"].get("address_claim")
    return None if claim is None else dict(claim["fields"])


async def test_a_new_owner_of_the_units_address_is_reported(
    db_url: str,
    names: tuple[j1939.Name, j1939.Name],
    stack: list[j1939.ElectronicControlUnit],
) -> None:
    old, new = names
    async with served(db_url, vehicles=1) as s:
        channel = s.sim.vehicle(VEHICLE).channel
        _claim_from(stack, channel, old)

        async def first() -> dict[str, Any] | None:
            return await _claim_value(s)

        assert await wait_for(first, what="the unit's NAME") == {
            "name": f"0x{old.value:016X}",
            "previous_name": None,
            "owner_changed": False,
        }
        _claim_from(stack, channel, new)

        async def changed() -> dict[str, Any] | None:
            value = await _claim_value(s)
            return value if value and value["owner_changed"] else None

        assert await wait_for(changed, what="the change of owner") == {
            "name": f"0x{new.value:016X}",
            "previous_name": f"0x{old.value:016X}",
            "owner_changed": True,
        }

        async def stored() -> list[Any]:
            rows = query(
                db_url,
                "SELECT m.fields FROM messages m JOIN units u ON u.id = m.unit_id "
                "WHERE u.sa = :sa AND m.name = 'address_claim' ORDER BY m.ts",
                sa=UNIT,
            )
            return rows if len(rows) == 2 else []

        rows = await wait_for(stored, what="both claims in the database")
        assert "owner_changed" in str(rows[1][0]) and "true" in str(rows[1][0]).lower()

        # The unit shows the NAME holding its address, live and in its history, and the
        # history tells which NAME each period is from.
        r = await s.client.get(f"/api/v1/vehicles/{VEHICLE}/live", headers=s.auth())
        (unit,) = [u for u in r.json()["units"] if u["sa"] == UNIT]
        assert unit["name"] == unit["summary"]["name"] == f"0x{new.value:016X}"

        answers: list[str] = []  # the history's answers other than 200 (a loaded machine)

        async def owners() -> list[Any]:
            r = await s.client.get(
                f"/api/v1/vehicles/{VEHICLE}/history",
                params={
                    "unit": UNIT,
                    "from": time.time() - 86400,
                    "to": time.time() + 86400,
                    "bucket": "1h",
                },
                headers=s.auth(),
            )
            if r.status_code != 200:
                answers.append(f"{r.status_code} {r.text}")
                return []
            body = r.json()
            return body["owners"] if len(body["owners"]) == 2 else []

        try:
            first_period, second_period = await wait_for(owners, what="both owners in the history")
        except AssertionError as exc:
            raise AssertionError(f"{exc}; answers other than 200: {answers[-3:]}") from exc
        # On the way, only answers a client retries: nothing stored yet (404 no_data, before
        # the writer's first batch on a loaded machine), the database busy (503).
        assert all(a.startswith(("503 ", '404 {"type":"no_data"')) for a in answers), answers
        assert first_period["name"] == f"0x{old.value:016X}"
        assert second_period["name"] == f"0x{new.value:016X}" and second_period["to"] is None
        assert first_period["to"] == second_period["from"]

        async def named() -> bool:
            rows = query(db_url, "SELECT name FROM units WHERE sa = :sa", sa=UNIT)
            return rows == [(f"0x{new.value:016X}",)]

        await wait_for(named, what="the unit row's NAME")
