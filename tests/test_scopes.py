"""Key scopes: a key sees and commands only the vehicles of its depots and vehicle ids; a
vehicle or object outside its scope is a 404 like one that does not exist. A matrix of
role x scope x endpoint on both engines, the websocket, scoped admins and fleet-wide routes."""

from __future__ import annotations

import time
from collections.abc import AsyncIterator
from contextlib import AbstractAsyncContextManager
from typing import Any

import orjson
import pytest
import pytest_asyncio
import websockets

from eqgw.alerts import repository as aq
from eqgw.config import VehicleConfig
from tests.api_helpers import Served, served, uvicorn_serving, ws_sync, ws_until

# SIM-001 and SIM-002 are at the north depot, SIM-003 at the south one.
DEPOTS = {"SIM-001": "north", "SIM-002": "north", "SIM-003": "south"}
VEHICLES = tuple(DEPOTS)
SCOPES: dict[str, Any] = {
    "all": "all",
    "north": {"groups": ["north"]},
    "sim3": {"vehicles": ["SIM-003"]},
    "north+sim3": {"groups": ["north"], "vehicles": ["SIM-003"]},
}
IN_SCOPE = {
    "all": set(VEHICLES),
    "north": {"SIM-001", "SIM-002"},
    "sim3": {"SIM-003"},
    "north+sim3": set(VEHICLES),
}
ROLES = ("viewer", "operator", "admin")
RANK = {r: i for i, r in enumerate(ROLES)}


def served_depots(db_url: str, **api: Any) -> AbstractAsyncContextManager[Served]:
    """Three simulated vehicles in two depots, served in-process (`api`: API settings)."""
    vehicles = [VehicleConfig(id=v, name=v, depot=d) for v, d in DEPOTS.items()]
    return served(db_url, config={"vehicles": vehicles}, **{"write_rate": 1000, **api})


# (method, path, body, the role it needs). {v} is the vehicle; {c} a command of it, {a} an
# alert of it, {m} a mute of it.
VEHICLE_ENDPOINTS: list[tuple[str, str, dict[str, Any] | None, str]] = [
    ("GET", "/vehicles/{v}/live", None, "viewer"),
    ("GET", "/vehicles/{v}/history", None, "viewer"),
    ("GET", "/vehicles/{v}/history?format=csv", None, "viewer"),
    ("GET", "/vehicles/{v}/status", None, "viewer"),
    ("GET", "/vehicles/{v}/faults", None, "viewer"),
    (
        "POST",
        "/vehicles/{v}/commands",
        {"all_units": True, "can_onoff_enable": True, "expires_in_s": 1},
        "operator",
    ),
    (
        "POST",
        "/vehicles/{v}/parameters",
        {"all_units": True, "fault_timer_s": 10, "expires_in_s": 1},
        "operator",
    ),
    ("POST", "/vehicles/{v}/requests", {"unit": 30, "what": "dm1", "expires_in_s": 1}, "operator"),
    ("GET", "/commands/{c}", None, "viewer"),
    ("GET", "/alerts/{a}", None, "viewer"),
    ("POST", "/alerts/{a}/acknowledge", {"comment": "seen"}, "operator"),
    ("POST", "/alerts/mutes", {"vehicle_id": "{v}", "duration_s": 60}, "admin"),
    ("DELETE", "/alerts/mutes/{m}", None, "admin"),
    ("DELETE", "/commands/{c}", None, "operator"),
]
# Listings: (path, how to take the vehicle ids out of the answer, the role it needs).
LISTINGS: list[tuple[str, Any, str]] = [
    ("/vehicles", lambda j: [v["id"] for v in j["vehicles"]], "viewer"),
    ("/faults", lambda j: [e["vehicle_id"] for e in j["episodes"]], "viewer"),
    ("/alerts", lambda j: [a["vehicle_id"] for a in j["alerts"]], "viewer"),
    ("/commands", lambda j: [c["vehicle_id"] for c in j], "viewer"),
    ("/audit?limit=10000", lambda j: [e["vehicle_id"] for e in j["entries"]], "operator"),
    ("/alerts/mutes", lambda j: [m["vehicle_id"] for m in j["mutes"]], "viewer"),
]


async def _objects(s: Served) -> dict[str, dict[str, str]]:
    """Per vehicle: a pending command, an open alert and a mute, made by the fleet admin."""
    out: dict[str, dict[str, str]] = {}
    admin = s.auth()
    for i, vid in enumerate(VEHICLES):
        r = await s.client.post(
            f"/api/v1/vehicles/{vid}/commands",
            json={"all_units": True, "can_onoff_enable": True, "expires_in_s": 300},
            headers=admin,
        )
        assert r.status_code == 202, r.text
        unit = next(iter(s.rt.ingest.live.of_vehicle(vid)))

        def raise_one(
            conn: Any, vid: str = vid, bus: str = unit.ref.bus, i: int = i
        ) -> dict[str, Any]:
            alert, _ = aq.raise_alert(
                conn,
                vehicle_id=vid,
                bus=bus,
                sa=200 + i,
                rule="imbalance",
                severity="warning",
                message="test",
                values={},
                ts=time.time(),
                muted=False,
            )
            return alert

        alert = await s.rt.db(raise_one)
        m = await s.client.post(
            "/api/v1/alerts/mutes", json={"vehicle_id": vid, "duration_s": 600}, headers=admin
        )
        assert m.status_code == 201, m.text
        out[vid] = {"c": r.json()["id"], "a": str(alert["id"]), "m": str(m.json()["id"])}
    return out


def _fill(text: str, vid: str, objs: dict[str, dict[str, str]]) -> str:
    ids = objs.get(vid, {"c": "00000000-0000-0000-0000-000000000000", "a": "999999", "m": "999999"})
    return (
        text.replace("{v}", vid)
        .replace("{c}", ids["c"])
        .replace("{a}", ids["a"])
        .replace("{m}", ids["m"])
    )


def _body(body: dict[str, Any] | None, vid: str) -> dict[str, Any] | None:
    if body is None:
        return None
    return {k: (vid if v == "{v}" else v) for k, v in body.items()}


_HIDDEN = {"unknown_vehicle", "unknown_command", "unknown_alert", "not_found"}


async def _matrix(s: Served) -> list[str]:
    objs = await _objects(s)
    failures: list[str] = []
    for role in ROLES:
        for scope_name, scope in SCOPES.items():
            r = await s.client.post(
                "/api/v1/keys",
                json={"name": f"{role}-{scope_name}", "role": role, "scope": scope},
                headers=s.auth(),
            )
            assert r.status_code == 201, r.text
            key = s.auth(r.json()["key"])
            # Mutes are made anew for each cancel: one cancelled is a 404 to anyone, which
            # would hide whether the scope let the key through. (A cancelled command is a
            # 409, an acknowledged alert too: inside the scope, the key was let through.)
            key_objs = {vid: dict(o) for vid, o in objs.items()}
            for method, path, body, needs in VEHICLE_ENDPOINTS:
                for vid in (*VEHICLES, "NOPE-999"):
                    if "{m}" in path and vid != "NOPE-999":
                        key_objs[vid] = await _fresh(s, vid, key_objs[vid])
                    url = "/api/v1" + _fill(path, vid, key_objs)
                    resp = await s.client.request(method, url, json=_body(body, vid), headers=key)
                    what = f"{role}/{scope_name} {method} {url}: {resp.status_code} {resp.text}"
                    kind = (
                        resp.json().get("type")
                        if resp.content
                        and resp.headers.get("content-type", "").startswith("application/json")
                        and isinstance(resp.json(), dict)
                        else None
                    )
                    if RANK[role] < RANK[needs]:
                        if resp.status_code != 403:
                            failures.append("role not refused: " + what)
                    elif vid == "NOPE-999" or vid not in IN_SCOPE[scope_name]:
                        if resp.status_code != 404 or kind not in _HIDDEN:
                            failures.append("outside the scope, not a 404: " + what)
                    elif resp.status_code in (401, 403) or (
                        resp.status_code == 404 and kind in _HIDDEN
                    ):
                        failures.append("inside the scope, refused: " + what)
            for path, ids_of, needs in LISTINGS:
                resp = await s.client.get("/api/v1" + path, headers=key)
                what = f"{role}/{scope_name} GET {path}: {resp.status_code}"
                if RANK[role] < RANK[needs]:
                    if resp.status_code != 403:
                        failures.append("role not refused: " + what)
                    continue
                if resp.status_code != 200:
                    failures.append("listing refused: " + what + resp.text)
                    continue
                seen = {v for v in ids_of(resp.json()) if v is not None}
                if scope_name == "all":  # refusals about unknown vehicles are audited too
                    seen.discard("NOPE-999")
                if seen - IN_SCOPE[scope_name]:
                    failures.append(f"listing shows {sorted(seen - IN_SCOPE[scope_name])}: {what}")
                if path in ("/vehicles", "/alerts", "/commands") and seen != IN_SCOPE[scope_name]:
                    failures.append(f"listing misses {IN_SCOPE[scope_name] - seen}: {what}")
    return failures


async def _fresh(s: Served, vid: str, ids: dict[str, str]) -> dict[str, str]:
    """A new mute of `vid` (made by the fleet admin): one cancelled is a 404 to anyone."""
    m = await s.client.post(
        "/api/v1/alerts/mutes", json={"vehicle_id": vid, "duration_s": 600}, headers=s.auth()
    )
    assert m.status_code == 201, m.text
    return {**ids, "m": str(m.json()["id"])}


async def test_scope_matrix(db_url: str) -> None:
    """Every (role, scope) against every endpoint naming a vehicle or one of its objects, on
    vehicles inside and outside the scope, and every listing: the role refuses first (403),
    then the scope hides (404, as for a vehicle that does not exist), inside it works."""
    async with served_depots(db_url) as s:
        failures = await _matrix(s)
    assert not failures, "\n".join(failures)


async def test_scoped_admin_keys_and_fleet_wide_routes(db_url: str) -> None:
    """A depot admin creates keys only within its scope, lists and revokes only those, and
    cannot touch what acts on the whole fleet (rules, webhooks, fleet-wide mutes)."""
    async with served_depots(db_url) as s:
        c = s.client
        r = await c.post(
            "/api/v1/keys",
            json={"name": "north admin", "role": "admin", "scope": {"groups": ["north"]}},
            headers=s.auth(),
        )
        assert r.status_code == 201 and r.json()["scope"] == {"groups": ["north"], "vehicles": []}
        north = s.auth(r.json()["key"])
        me = (await c.get("/api/v1/me", headers=north)).json()
        assert me["scope"] == {"groups": ["north"], "vehicles": []}
        # Wider than its own: refused.
        for scope in ("all", {"groups": ["south"]}, {"vehicles": ["SIM-003"]},
                      {"groups": ["north", "south"]}):  # fmt: skip
            r = await c.post(
                "/api/v1/keys", json={"name": "x", "role": "viewer", "scope": scope}, headers=north
            )
            assert r.status_code == 403, (scope, r.text)
        # Within: a vehicle of its depot, the depot itself, or (omitted) its own scope.
        r = await c.post(
            "/api/v1/keys",
            json={"name": "sim1", "role": "operator", "scope": {"vehicles": ["SIM-001"]}},
            headers=north,
        )
        assert r.status_code == 201, r.text
        r = await c.post("/api/v1/keys", json={"name": "dflt", "role": "viewer"}, headers=north)
        assert r.status_code == 201 and r.json()["scope"]["groups"] == ["north"]
        # A south key made by the fleet admin is invisible to the north admin.
        r = await c.post(
            "/api/v1/keys",
            json={"name": "south", "role": "viewer", "scope": {"groups": ["south"]}},
            headers=s.auth(),
        )
        south_id = r.json()["id"]
        listed = {k["name"] for k in (await c.get("/api/v1/keys", headers=north)).json()}
        assert listed == {"north admin", "sim1", "dflt"}
        assert (await c.delete(f"/api/v1/keys/{south_id}", headers=north)).status_code == 404
        r = await c.post(f"/api/v1/keys/{south_id}/rotate", json={}, headers=north)
        assert r.status_code == 404
        # Fleet-wide things.
        rule = {"id": "x1", "kind": "imbalance", "severity": "info", "params": {}}
        assert (await c.post("/api/v1/alerts/rules", json=rule, headers=north)).status_code == 403
        r = await c.patch("/api/v1/alerts/rules/imbalance", json={"enabled": False}, headers=north)
        assert r.status_code == 403
        assert (await c.get("/api/v1/webhooks", headers=north)).status_code == 403
        hook = {"name": "h", "url": "http://127.0.0.1:9/x"}
        assert (await c.post("/api/v1/webhooks", json=hook, headers=north)).status_code == 403
        r = await c.post("/api/v1/alerts/mutes", json={"duration_s": 60}, headers=north)
        assert r.status_code == 403
        # The fleet admin still can (the checks are the scope's, not the role's).
        assert (await c.get("/api/v1/webhooks", headers=s.auth())).status_code == 200


async def test_websocket_is_limited_to_the_scope(db_url: str) -> None:
    """Snapshots and events of vehicles outside the key's scope never reach its websocket,
    whatever it subscribes to: by the query string, by a list of vehicles, by `*`."""
    async with served_depots(db_url) as s:
        r = await s.client.post(
            "/api/v1/keys",
            json={"name": "sim3", "role": "viewer", "scope": {"vehicles": ["SIM-003"]}},
            headers=s.auth(),
        )
        key = r.json()["key"]
        async with uvicorn_serving(s.app) as port:
            url = f"ws://127.0.0.1:{port}/api/v1/ws?key={key}&vehicles=SIM-001,SIM-003"
            async with websockets.connect(url) as ws:
                seen: list[dict[str, Any]] = []
                # The query string's vehicles: the snapshot of SIM-003 alone.
                seen += await ws_until(ws, lambda m: m.get("vehicle_id") == "SIM-003")
                for vehicles in (list(VEHICLES), "*", ["SIM-001"]):
                    # Text frames, as a client sends them (a binary frame is refused before
                    # the subscribe is looked at).
                    message = {"type": "subscribe", "vehicles": vehicles}
                    await ws.send(orjson.dumps(message).decode())
                    seen += await ws_sync(ws)
                # The subscription still holds SIM-003's events, and only those.
                seen += await ws_until(
                    ws, lambda m: m["type"] != "snapshot" and m.get("vehicle_id") == "SIM-003"
                )
                ids = {m["vehicle_id"] for m in seen if "vehicle_id" in m}
                assert ids == {"SIM-003"}, sorted(ids)
                snapshots = [m for m in seen if m["type"] == "snapshot"]
                # `*` sends the snapshots of the whole scope again: SIM-003's.
                assert len(snapshots) >= 2, [m["type"] for m in seen]


@pytest_asyncio.fixture(scope="module", loop_scope="module")
async def depots(module_db_url: str) -> AsyncIterator[Served]:
    """One gateway for the tests that are refused and change nothing."""
    async with served_depots(module_db_url) as s:
        yield s


@pytest.mark.asyncio(loop_scope="module")
@pytest.mark.parametrize("scope", [{"groups": []}, {"vehicles": []}, {}])
async def test_an_empty_scope_is_refused(depots: Served, scope: dict[str, Any]) -> None:
    r = await depots.client.post(
        "/api/v1/keys", json={"name": "x", "role": "viewer", "scope": scope}, headers=depots.auth()
    )
    assert r.status_code == 422, r.text


async def test_readyz_and_metrics_tell_a_scoped_key_nothing_of_other_depots(db_url: str) -> None:
    """/readyz and /metrics describe the whole gateway (every bus, the cluster, webhooks): a
    key scoped to depots or vehicles gets what an anonymous caller gets, whatever its role,
    so it never learns another depot's bus names, vehicle ids or errors there. A whole-fleet
    admin still reads the details."""
    async with served_depots(db_url, metrics_token="scrape-me") as s:
        anon_ready = (await s.client.get("/readyz")).json()
        assert anon_ready == {"ready": True}
        for role in (*ROLES, "ingest"):
            for scope_name in ("north", "sim3"):
                r = await s.client.post(
                    "/api/v1/keys",
                    json={"name": f"{role}-{scope_name}", "role": role,
                          "scope": SCOPES[scope_name]},
                    headers=s.auth(),
                )  # fmt: skip
                assert r.status_code == 201, r.text
                key = s.auth(r.json()["key"])
                others = set(VEHICLES) - IN_SCOPE[scope_name]
                ready = await s.client.get("/readyz", headers=key)
                metrics = await s.client.get("/metrics", headers=key)
                what = f"{role}/{scope_name}"
                assert ready.json() == anon_ready, (what, ready.text)
                assert metrics.status_code == 200, (what, metrics.text)
                assert 'bus="' not in metrics.text, (what, metrics.text)
                for body in (ready.text, metrics.text):
                    assert not [v for v in others if v in body], (what, body)
        full = await s.client.get("/readyz", headers=s.auth())
        assert "SIM-003/sim" in full.text and "SIM-001/sim" in full.text
        assert 'bus="SIM-003/sim"' in (await s.client.get("/metrics", headers=s.auth())).text
