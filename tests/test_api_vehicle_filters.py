"""`GET /vehicles` filtered by depot, state and search, and paged, on both engines: a page holds
what was asked, `total` counts every match, `counts` the states, the unfiltered answer keeps
its shape (plus `total`), a scoped key's filters stay inside its scope, bad filters are 422."""

from __future__ import annotations

from eqgw.config import VehicleConfig
from tests.api_helpers import served, wait_for

API = "/api/v1"
DEPOTS = {"SIM-001": "north", "SIM-002": "north", "SIM-003": "south", "SIM-004": "south"}
NAMES = {"SIM-001": "Northern Star", "SIM-002": "Polar Express", "SIM-003": "Southern Cross",
         "SIM-004": "Cape Horn"}  # fmt: skip


async def test_vehicles_filters_and_paging(db_url: str) -> None:
    vehicles = [VehicleConfig(id=v, name=NAMES[v], depot=d) for v, d in DEPOTS.items()]
    async with served(db_url, vehicles=4, config={"vehicles": vehicles}) as s:
        c = s.client

        async def get(**params: object) -> dict:  # type: ignore[type-arg]
            r = await c.get(f"{API}/vehicles", params=params, headers=s.auth())
            assert r.status_code == 200, r.text
            body: dict = r.json()  # type: ignore[type-arg]
            return body

        async def four() -> bool:
            return len((await get())["vehicles"]) == 4

        await wait_for(four, what="four vehicles listed")
        every = await get()
        assert every["total"] == 4 and every["offset"] == 0 and every["limit"] is None
        assert [v["id"] for v in every["vehicles"]] == sorted(DEPOTS)
        assert every["vehicles"][0]["units"], "the unfiltered listing keeps its units"

        north = await get(depot="north")
        assert [v["id"] for v in north["vehicles"]] == ["SIM-001", "SIM-002"]
        assert north["total"] == 2 and sum(north["counts"].values()) == 2

        # Search: id, name or depot, any case.
        assert [v["id"] for v in (await get(search="cross"))["vehicles"]] == ["SIM-003"]
        assert [v["id"] for v in (await get(search="sim-00"))["vehicles"]] == sorted(DEPOTS)
        assert [v["id"] for v in (await get(search="SOUTH"))["vehicles"]] == ["SIM-003", "SIM-004"]
        assert (await get(search="nothing like it"))["total"] == 0

        # Paging: pages in id order, `total` is every match.
        p1 = await get(limit=3)
        p2 = await get(limit=3, offset=3)
        assert [v["id"] for v in p1["vehicles"] + p2["vehicles"]] == sorted(DEPOTS)
        assert p1["total"] == p2["total"] == 4 and p1["limit"] == 3 and p2["offset"] == 3

        # State: the vehicles in those states, the counts of all states.
        states = {v["id"]: v["state"] for v in every["vehicles"]}
        some = next(iter(states.values()))
        by_state = await get(state=some)
        assert {v["id"] for v in by_state["vehicles"]} == {
            i for i, st in states.items() if st == some
        }
        assert by_state["counts"][some] == by_state["total"]
        assert sum(by_state["counts"].values()) == 4
        both = await get(state="ok,attention,offline,parked,not_reporting")
        assert both["total"] == 4

        for bad in ({"state": "fine"}, {"limit": 0}, {"offset": -1}, {"limit": 100_000}):
            r = await c.get(f"{API}/vehicles", params=bad, headers=s.auth())
            assert r.status_code == 422, (bad, r.text)
        r = await c.get(f"{API}/vehicles", params={"state": "fine"}, headers=s.auth())
        assert r.json()["type"].endswith("invalid_state") or "fine" in r.text

        # A key scoped to the north depot: the south's vehicles are not there to find.
        r = await c.post(
            f"{API}/keys",
            json={"name": "north only", "role": "viewer", "scope": {"groups": ["north"]}},
            headers=s.auth(),
        )
        assert r.status_code == 201, r.text
        scoped = r.json()["key"]
        r = await c.get(f"{API}/vehicles", params={"search": "south"}, headers=s.auth(scoped))
        assert r.status_code == 200 and r.json()["total"] == 0
        r = await c.get(f"{API}/vehicles", params={"limit": 10}, headers=s.auth(scoped))
        assert [v["id"] for v in r.json()["vehicles"]] == ["SIM-001", "SIM-002"]
