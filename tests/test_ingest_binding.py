"""Ingest keys are bound to vehicles: a key posts frames only for the vehicles of its scope,
a stream belongs to the key that first uploaded it (and the keys rotated from it), anything
else is a 403 and nothing of it is stored. Both engines."""

from __future__ import annotations

import time
from typing import Any

from sqlalchemy import func, select

from eqgw.security.keys import Scope, create_key
from eqgw.store.models import Unit
from tests.api_helpers import Served, served


def _body(stream: str, vehicle: str, bus: str | None = None, first: int = 1) -> dict[str, Any]:
    body: dict[str, Any] = {
        "stream": stream,
        "vehicle": vehicle,
        "first_seq": first,
        "frames": [[time.time() - 5 + i, 0x18FFD61E, "d809b013ba7cc87d", 1] for i in range(5)],
    }
    if bus is not None:
        body["bus"] = bus
    return body


async def _units_on(s: Served, bus: str) -> int:
    def run(conn: Any) -> int:
        n: int = conn.execute(
            select(func.count()).select_from(Unit).where(Unit.bus == bus)
        ).scalar_one()
        return n

    n: int = await s.rt.db(run)
    return n


async def test_an_ingest_key_posts_only_for_its_vehicles_and_streams(db_url: str) -> None:
    async with served(db_url, vehicles=2) as s:
        engine = s.rt.engine
        _, bound = create_key(engine, "bus 1", "ingest", scope=Scope.of([], ["SIM-001"]))
        other_id, other = create_key(
            engine, "bus 1 spare", "ingest", scope=Scope.of([], ["SIM-001"])
        )
        c = s.client

        def auth(k: str) -> dict[str, str]:
            return {"Authorization": f"Bearer {k}"}

        # The forgery: frames for another vehicle under a new bus name.
        r = await c.post(
            "/api/v1/ingest/frames",
            json=_body("s-forged", "SIM-002", "SIM-002/x"),
            headers=auth(bound),
        )
        assert r.status_code == 403, r.text
        assert await _units_on(s, "SIM-002/x") == 0
        # Its own vehicle: stored.
        r = await c.post(
            "/api/v1/ingest/frames", json=_body("s1", "SIM-001", "SIM-001/fwd"), headers=auth(bound)
        )
        assert r.status_code == 200, r.text
        assert r.json()["acked_seq"] == 5
        assert await _units_on(s, "SIM-001/fwd") == 1
        # The same stream from another key bound to the same vehicle: a stream has one key.
        r = await c.post(
            "/api/v1/ingest/frames",
            json=_body("s1", "SIM-001", "SIM-001/fwd", 6),
            headers=auth(other),
        )
        assert r.status_code == 403, r.text
        # Its own stream of the same vehicle is fine.
        r = await c.post(
            "/api/v1/ingest/frames",
            json=_body("s2", "SIM-001", "SIM-001/fwd2"),
            headers=auth(other),
        )
        assert r.status_code == 200, r.text
        # A refusal is audited.
        audit = (await c.get("/api/v1/audit", headers=s.auth())).json()["entries"]
        assert any(
            e["action"] == "ingest.frames"
            and e["status_code"] == 403
            and e["vehicle_id"] == "SIM-002"
            for e in audit
        )
        # Rotation: the new key continues the old key's stream.
        r = await c.post(f"/api/v1/keys/{other_id}/rotate", json={"overlap_s": 0}, headers=s.auth())
        assert r.status_code == 201, r.text
        rotated = r.json()["key"]
        r = await c.post(
            "/api/v1/ingest/frames",
            json=_body("s2", "SIM-001", "SIM-001/fwd2", 6),
            headers=auth(rotated),
        )
        assert r.status_code == 200 and r.json()["acked_seq"] == 10, r.text
        # The stream's owner survives a restart of the service (it is in the database).
        s.app.state.forward_ingest._streams.clear()
        r = await c.post(
            "/api/v1/ingest/frames",
            json=_body("s2", "SIM-001", "SIM-001/fwd2", 11),
            headers=auth(bound),
        )
        assert r.status_code == 403, r.text


async def test_an_unbound_ingest_key_is_bound_by_rotation(db_url: str) -> None:
    """A key of the whole fleet (made before scopes) rotated into one bound to its vehicle:
    the forwarder's stream goes on with the new key; a wider scope is refused."""
    async with served(db_url, vehicles=2) as s:
        old_id, old = create_key(s.rt.engine, "legacy", "ingest")
        c = s.client
        hdr = {"Authorization": f"Bearer {old}"}
        r = await c.post(
            "/api/v1/ingest/frames", json=_body("s9", "SIM-001", "SIM-001/f"), headers=hdr
        )
        assert r.status_code == 200, r.text
        r = await c.post(
            f"/api/v1/keys/{old_id}/rotate",
            json={"overlap_s": 0, "scope": {"vehicles": ["SIM-001"]}},
            headers=s.auth(),
        )
        assert r.status_code == 201 and r.json()["scope"] == {"groups": [], "vehicles": ["SIM-001"]}
        new = {"Authorization": f"Bearer {r.json()['key']}"}
        r = await c.post(
            "/api/v1/ingest/frames", json=_body("s9", "SIM-001", "SIM-001/f", 6), headers=new
        )
        assert r.status_code == 200 and r.json()["acked_seq"] == 10, r.text
        r = await c.post(
            "/api/v1/ingest/frames", json=_body("s10", "SIM-002", "SIM-002/f"), headers=new
        )
        assert r.status_code == 403
        # Rotation never widens a key.
        bound_id = (await c.get("/api/v1/keys", headers=s.auth())).json()[-1]["id"]
        r = await c.post(
            f"/api/v1/keys/{bound_id}/rotate",
            json={"scope": {"vehicles": ["SIM-001", "SIM-002"]}},
            headers=s.auth(),
        )
        assert r.status_code == 422, r.text


async def test_an_ingest_key_needs_a_scope_or_the_explicit_fleet_flag(db_url: str) -> None:
    """`POST /keys` of an ingest key without a scope made a key that uploads for every
    vehicle (one leaked forwarder key then forges any vehicle's frames). It needs vehicles or
    depots, or the explicit fleet-wide `{"all": true}`; keys of other roles are unchanged, and
    a fleet-wide ingest key made before (no scope stored) keeps working."""
    async with served(db_url, vehicles=2) as s:
        c, admin = s.client, s.auth()
        legacy_id, legacy = create_key(s.rt.engine, "legacy relay", "ingest")

        async def make(name: str, role: str, scope: Any) -> Any:
            body = {"name": name, "role": role, "scope": scope}
            return await c.post("/api/v1/keys", json=body, headers=admin)

        r = await c.post("/api/v1/keys", json={"name": "fwd", "role": "ingest"}, headers=admin)
        assert r.status_code == 422, r.text
        detail = r.json()["detail"]
        assert "ingest" in detail and '{"all": true}' in detail, detail
        for scope in ({"all": False}, {"all": True, "vehicles": ["SIM-001"]}, {"all": 1}):
            r = await make("fwd", "ingest", scope)
            assert r.status_code == 422, (scope, r.text)
        names = [k["name"] for k in (await c.get("/api/v1/keys", headers=admin)).json()]
        assert "fwd" not in names
        r = await make("bound", "ingest", {"vehicles": ["SIM-001"]})
        assert r.status_code == 201, r.text
        for scope in ({"all": True}, "all"):
            r = await make("relay", "ingest", scope)
            assert r.status_code == 201 and r.json()["scope"] is None, r.text
        relay = r.json()["key"]
        # Other roles: no scope is the creator's (here the whole fleet), as before.
        r = await c.post("/api/v1/keys", json={"name": "v", "role": "viewer"}, headers=admin)
        assert r.status_code == 201 and r.json()["scope"] is None, r.text
        r = await make("v2", "viewer", {"all": True})
        assert r.status_code == 201 and r.json()["scope"] is None, r.text
        # The explicit relay and the key made before the rule both upload for any vehicle.
        for n, key in enumerate((relay, legacy)):
            hdr = {"Authorization": f"Bearer {key}"}
            r = await c.post("/api/v1/ingest/frames", json=_body(f"r{n}", "SIM-002", "SIM-002/f"),
                             headers=hdr)  # fmt: skip
            assert r.status_code == 200, r.text
        listed = {k["id"]: k for k in (await c.get("/api/v1/keys", headers=admin)).json()}
        assert listed[legacy_id]["scope"] is None and listed[legacy_id]["active"]
