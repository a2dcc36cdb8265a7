"""Every operation of `app.openapi()` and every websocket message type, with keys scoped to one
depot or one vehicle, of each role, on SQLite and PostgreSQL: nothing of another depot's
vehicles (id, name, bus name) comes back, a request naming one is answered exactly as one
naming a vehicle that does not exist, and a write to one is refused.

The routes and their parameters come from the OpenAPI document and the message types from
`ClientMessage`: a new route, path parameter, request body or message type that the walk
cannot fill makes it fail until it is taught (PATH_VALUES, QUERY_VALUES, BODIES,
_ws_messages), so nothing is left out silently. One gateway per engine serves the whole walk.
"""

from __future__ import annotations

import asyncio
import re
import time
import uuid
from collections.abc import AsyncIterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import httpx
import orjson
import pytest
import pytest_asyncio
import websockets
from sqlalchemy import text

from eqgw.alerts import repository as aq
from eqgw.api.ws import ClientMessage
from eqgw.config import VehicleConfig
from eqgw.ingest.events import LIVE, Event, UnitRef
from eqgw.security.auth import Viewer
from tests.api_helpers import Served, served, uvicorn_serving, ws_sync, ws_until
from tests.conftest import PG_ADMIN_URL, pg_unavailable_reason

pytestmark = pytest.mark.asyncio(loop_scope="module")

# Two depots; names and bus names unlike the ids, so each is looked for on its own.
DEPOTS = {"SIM-001": "north", "SIM-002": "north", "SIM-003": "south"}
NAMES = {"SIM-001": "Northern Star", "SIM-002": "Polar Express", "SIM-003": "Southern Cross"}
NOPE = "NOPE-999"  # a vehicle that does not exist
# A scope of each kind, and the other-depot vehicle its requests name.
SCOPES: dict[str, tuple[dict[str, list[str]], str]] = {
    "depot": ({"groups": ["north"]}, "SIM-003"),
    "vehicle": ({"vehicles": ["SIM-003"]}, "SIM-001"),
}
IN_SCOPE = {"depot": {"SIM-001", "SIM-002"}, "vehicle": {"SIM-003"}}
ROLES = ("viewer", "operator", "admin", "ingest")

# Placeholders: {v} a vehicle, {c} a command of it, {a} an alert of it, {m} a mute of it, {k}
# a key scoped to it; {key} the calling key, {rule} and {hook} an alert rule and a webhook
# (fleet-wide objects), {stream} a forwarder stream of the calling key.
NAMING = ("{v}", "{c}", "{a}", "{m}", "{k}")
PATH_VALUES = {
    "vehicle_id": "{v}",
    "command_id": "{c}",
    "alert_id": "{a}",
    "mute_id": "{m}",
    "key_id": "{k}",
    "rule_id": "{rule}",
    "webhook_id": "{hook}",
}
# Optional query parameters that name a vehicle or its objects: asked without, then with.
QUERY_VALUES = {"vehicle": "{v}", "key_id": "{k}"}
# A valid body per request schema (the fleet admin's control below proves they are valid).
BODIES: dict[str, Any] = {
    "ControlCommand": {"all_units": True, "jump_start_override": True, "expires_in_s": 5},
    "ParameterWrite": {"all_units": True, "fault_timer_s": 10, "expires_in_s": 5},
    "DeviceRequest": {"unit": 30, "what": "dm1", "expires_in_s": 5},
    "KeyCreate": {"name": "walk key", "role": "viewer", "scope": {"vehicles": ["{v}"]}},
    "KeyRotate": {"overlap_s": 3600},
    "RuleIn": {"id": "walk-rule", "kind": "imbalance", "severity": "info", "params": {}},
    "RulePatch": {"enabled": True},
    "MuteIn": {"vehicle_id": "{v}", "duration_s": 60},
    "Acknowledge": {"comment": "walk"},
    "Login": {"key": "{key}"},
    "CodeQuery": {"code": "walk-no-such-code"},
    "FrameUpload": {
        "stream": "{stream}",
        "vehicle": "{v}",
        "first_seq": 1,
        "frames": [[0.0, 0x18FECA1E, "00FF000000FFFFFF", 1]],
    },
    "WebhookCreate": {"name": "walk hook", "url": "http://127.0.0.1:9/x", "vehicles": ["{v}"]},
    "WebhookUpdate": {"enabled": True},
    # Fleet management: a new vehicle in the other depot; a vehicle's depot set to its own
    # (a whole-fleet admin's change that changes nothing); an import naming the vehicle as
    # it is (a CSV body: text, not JSON).
    "VehicleCreate": {"id": "WALK-NEW", "depot": "south"},
    "VehiclePatch": {"depot": "south"},
    "text/csv": "vehicle_id,name,depot\n{v},Southern Cross,south\n",
}
WRITES = {"POST", "PUT", "PATCH", "DELETE"}


@dataclass
class Gateway:
    """The walk's gateway: the served app, its objects per vehicle, the keys, its port."""

    s: Served
    port: int
    objects: dict[str, dict[str, str]]  # vehicle -> placeholder -> value
    shared: dict[str, str]  # {rule}, {hook}
    keys: dict[tuple[str, str], str] = field(default_factory=dict)  # (role, scope) -> key


@dataclass(frozen=True)
class Request:
    method: str
    path: str
    query: dict[str, str]
    body: Any  # a template (placeholders), or None

    def naming(self) -> tuple[str, ...]:
        """The placeholders of a vehicle or its objects that the request holds."""
        blob = orjson.dumps([self.path, self.query, self.body]).decode()
        return tuple(p for p in NAMING if p in blob)

    def __str__(self) -> str:
        q = "&".join(f"{k}={v}" for k, v in self.query.items())
        return f"{self.method} {self.path}{'?' + q if q else ''}"


def _requests(spec: dict[str, Any]) -> list[Request]:
    """Every operation of the OpenAPI document as requests to make: with its path parameters
    and body filled, once without and once with each optional parameter naming a vehicle."""
    out: list[Request] = []
    for path, ops in spec["paths"].items():
        for method, op in ops.items():
            filled = path
            query: dict[str, str] = {}
            for p in op.get("parameters", []):
                if p["in"] == "path":
                    assert p["name"] in PATH_VALUES, f"teach the walk {p['name']} ({path})"
                    filled = filled.replace("{" + p["name"] + "}", PATH_VALUES[p["name"]])
                elif p["in"] == "query" and p["name"] in QUERY_VALUES:
                    query[p["name"]] = QUERY_VALUES[p["name"]]
                else:
                    assert not p.get("required"), f"teach the walk {p['name']} ({path})"
            body = None
            content = op.get("requestBody", {}).get("content", {})
            if "text/csv" in content:
                body = BODIES["text/csv"]
            elif content:
                ref = content["application/json"]["schema"]["$ref"].rsplit("/", 1)[-1]
                assert ref in BODIES, f"teach the walk a {ref} body ({method.upper()} {path})"
                body = BODIES[ref]
            out.append(Request(method.upper(), filled, {}, body))
            for name, value in query.items():
                out.append(Request(method.upper(), filled, {name: value}, body))
    return out


def _fill(template: Any, values: dict[str, str]) -> Any:
    if isinstance(template, str):
        for placeholder, value in values.items():
            template = template.replace(placeholder, value)
        return template
    if isinstance(template, list):
        return [_fill(t, values) for t in template]
    if isinstance(template, dict):
        return {k: _fill(v, values) for k, v in template.items()}
    return template


def _leaks(body: str, others: set[str], requested: dict[str, str]) -> list[str]:
    """What `body` says of the other depot's vehicles: their names and bus names anywhere,
    their ids anywhere but where the request itself named one (the answer to a vehicle that
    does not exist names it too)."""
    found = [s for v in others for s in (NAMES[v], f"{v}/sim") if s in body]
    for value in requested.values():
        body = body.replace(value, "<requested>")
    found += [v for v in others if v in body]
    return found


def _shape(r: httpx.Response, values: dict[str, str]) -> tuple[int, Any]:
    """The status and, for an error, its body with the request's own values masked: what must
    be the same for another depot's vehicle and one that does not exist."""
    if r.status_code < 400 or not r.headers.get("content-type", "").startswith("application/"):
        return r.status_code, None
    body = r.text
    for placeholder, value in sorted(values.items(), key=lambda pv: -len(pv[1])):
        body = re.sub(rf"(?<![\w-]){re.escape(value)}(?![\w-])", placeholder, body)
    return r.status_code, orjson.loads(body)


@pytest_asyncio.fixture(
    scope="module",
    loop_scope="module",
    params=["sqlite", pytest.param("postgres", marks=pytest.mark.postgres)],
)
async def gateway(
    request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory
) -> AsyncIterator[Gateway]:
    """One gateway per engine for the whole walk: three simulated vehicles in two depots,
    a command, an alert, a mute and a scoped key of each vehicle, a rule and a webhook, and a
    key of each role for each scope."""
    async with _database(request.param, tmp_path_factory.mktemp("walk")) as url:
        vehicles = [VehicleConfig(id=v, name=NAMES[v], depot=d) for v, d in DEPOTS.items()]
        config = {"vehicles": vehicles, "webhook_allow_networks": "127.0.0.0/8"}
        async with (
            served(url, config=config, write_rate=100_000) as s,
            uvicorn_serving(s.app) as port,
        ):
            gw = Gateway(s, port, await _objects(s), await _shared(s))
            for role in ROLES:
                for name, (scope, _) in SCOPES.items():
                    gw.keys[(role, name)] = await _key(s, f"walk {role} {name}", role, scope)
            gw.keys[("admin", "all")] = s.admin_key
            gw.keys[("ingest", "all")] = await _key(s, "walk fleet ingest", "ingest", "all")
            yield gw


class _database:
    """A fresh database of the engine: a SQLite file, or a PostgreSQL schema dropped after."""

    def __init__(self, engine: str, tmp: Path) -> None:
        self.engine, self.tmp, self.schema = engine, tmp, f"t_{uuid.uuid4().hex[:12]}"

    async def __aenter__(self) -> str:
        if self.engine == "sqlite":
            return f"sqlite:///{self.tmp / 'eqgw.db'}"
        reason = pg_unavailable_reason()
        if reason:
            pytest.skip(reason)
        await asyncio.to_thread(self._pg, f'CREATE SCHEMA "{self.schema}"')
        return f"{PG_ADMIN_URL}?options=-csearch_path%3D{self.schema}"

    async def __aexit__(self, *exc: object) -> None:
        if self.engine != "sqlite":
            await asyncio.to_thread(self._pg, f'DROP SCHEMA "{self.schema}" CASCADE')
            partitions = f"{self.schema}_partitions"  # eqgw.store.partitions
            await asyncio.to_thread(self._pg, f'DROP SCHEMA IF EXISTS "{partitions}" CASCADE')

    @staticmethod
    def _pg(sql: str) -> None:
        from eqgw.store.engine import create_engine

        admin = create_engine(PG_ADMIN_URL)
        try:
            with admin.begin() as conn:
                conn.execute(text(sql))
        finally:
            admin.dispose()


async def _key(s: Served, name: str, role: str, scope: Any) -> str:
    r = await s.client.post(
        "/api/v1/keys", json={"name": name, "role": role, "scope": scope}, headers=s.auth()
    )
    assert r.status_code == 201, r.text
    key: str = r.json()["key"]
    return key


async def _objects(s: Served) -> dict[str, dict[str, str]]:
    """Per vehicle, made by the fleet admin: a pending command, an open alert, a mute, and a
    key scoped to it (its creation audited with the vehicle in the request)."""
    out: dict[str, dict[str, str]] = {}
    admin = s.auth()
    for i, vid in enumerate(DEPOTS):
        r = await s.client.post(
            f"/api/v1/vehicles/{vid}/commands",
            json={"all_units": True, "can_onoff_enable": True, "expires_in_s": 300},
            headers=admin,
        )
        assert r.status_code == 202, r.text
        unit = next(iter(s.rt.ingest.live.of_vehicle(vid)))

        def raise_one(conn: Any, vid: str = vid, bus: str = unit.ref.bus, i: int = i) -> Any:
            alert, _ = aq.raise_alert(
                conn, vehicle_id=vid, bus=bus, sa=200 + i, rule="imbalance", severity="warning",
                message=f"imbalance on {NAMES[vid]}", values={}, ts=time.time(), muted=False,
            )  # fmt: skip
            return alert

        alert = await s.rt.db(raise_one)
        m = await s.client.post(
            "/api/v1/alerts/mutes", json={"vehicle_id": vid, "duration_s": 600}, headers=admin
        )
        assert m.status_code == 201, m.text
        k = await s.client.post(
            "/api/v1/keys",
            json={"name": f"seed {i}", "role": "viewer", "scope": {"vehicles": [vid]}},
            headers=admin,
        )
        assert k.status_code == 201, k.text
        out[vid] = {
            "{v}": vid,
            "{c}": r.json()["id"],
            "{a}": str(alert["id"]),
            "{m}": str(m.json()["id"]),
            "{k}": str(k.json()["id"]),
        }
    out[NOPE] = {
        "{v}": NOPE,
        "{c}": str(uuid.UUID(int=0)),
        "{a}": "999991",
        "{m}": "999992",
        "{k}": "999993",
    }
    return out


async def _shared(s: Served) -> dict[str, str]:
    """A rule and a webhook (fleet-wide: a scoped key of any role is refused them)."""
    rules = (await s.client.get("/api/v1/alerts/rules", headers=s.auth())).json()
    rule = rules[0]["id"] if isinstance(rules, list) else rules["rules"][0]["id"]
    hook = await s.client.post(
        "/api/v1/webhooks",
        json={"name": "south hook", "url": "http://127.0.0.1:9/x", "vehicles": ["SIM-003"]},
        headers=s.auth(),
    )
    assert hook.status_code == 201, hook.text
    return {"{rule}": str(rule), "{hook}": str(hook.json()["id"])}


async def _send(
    gw: Gateway, req: Request, key: str, values: dict[str, str]
) -> tuple[httpx.Response, dict[str, str]]:
    values = {**gw.shared, **values, "{key}": key, "{stream}": f"walk-{key[-12:]}"}
    url = _fill(req.path, values)
    params = _fill(req.query, values)
    body = _fill(req.body, values)
    if isinstance(body, dict) and "frames" in body:
        body["frames"] = [[time.time(), *f[1:]] for f in body["frames"]]
    headers = {"Authorization": f"Bearer {key}"}
    if isinstance(body, str):  # a CSV body
        r = await gw.s.client.request(
            req.method, url, params=params, content=body,
            headers={**headers, "content-type": "text/csv"},
        )  # fmt: skip
    else:
        r = await gw.s.client.request(req.method, url, params=params, json=body, headers=headers)
    gw.s.client.cookies.clear()  # a login's cookie must not ride on the next key's requests
    return r, values


# -- HTTP --------------------------------------------------------------------------------------


async def test_scoped_keys_learn_nothing_of_other_depots(gateway: Gateway) -> None:
    """Every route and every websocket message type, with a key of each role scoped to a
    depot and to a vehicle. One test per engine (the cases share its gateway, and under
    xdist each engine's gateway starts once); the failures of every case are listed."""
    failures = []
    try:
        await _check_bodies(gateway)
    except AssertionError as exc:
        failures.append(f"the walk's own requests: {exc}")
    for role in ROLES:
        for scope in SCOPES:
            for walk in (_walk_routes, _walk_websocket):
                try:
                    await walk(gateway, role, scope)
                except AssertionError as exc:
                    failures.append(f"{role} key scoped to a {scope}, {walk.__name__}: {exc}")
    assert not failures, "\n\n".join(failures)


async def _walk_routes(gw: Gateway, role: str, scope: str) -> None:
    """Every operation of the OpenAPI document: nothing of the other depot in any answer; a
    request naming its vehicle (or an object of it) answered as one naming a vehicle that does
    not exist; a write to it refused."""
    key = gw.keys[(role, scope)]
    other = SCOPES[scope][1]
    others = set(DEPOTS) - IN_SCOPE[scope]
    failures: list[str] = []
    requests = _requests(gw.s.app.openapi())
    assert len(requests) > 40, "the walk found too few routes"
    for req in requests:
        naming = req.naming()
        if not naming:
            r, values = await _send(gw, req, key, {})
            if leaks := _leaks(r.text, others, {}):
                failures.append(f"{req}: {r.status_code} shows {leaks}: {r.text[:300]}")
            continue
        r, values = await _send(gw, req, key, gw.objects[other])
        twin, twin_values = await _send(gw, req, key, gw.objects[NOPE])
        what = f"{req} on {other}: {r.status_code} {r.text[:300]}"
        requested = {p: values[p] for p in naming}
        if leaks := _leaks(r.text, others, requested):
            failures.append(f"shows {leaks}: {what}")
        twin_requested = {p: twin_values[p] for p in naming}
        if _shape(r, requested) != _shape(twin, twin_requested):
            failures.append(
                f"answered unlike a vehicle that does not exist ({twin.status_code} "
                f"{twin.text[:200]}): {what}"
            )
        if req.method in WRITES and r.status_code < 400:
            failures.append(f"a write to another depot's vehicle was accepted: {what}")
    assert not failures, "\n".join(failures)


async def _check_bodies(gw: Gateway) -> None:
    """Each write with a body that the walk sends naming a vehicle succeeds for a whole-fleet
    key (admin, or ingest for the forwarder's route): its refusal to scoped keys is the
    scope's doing, not a body that never was valid. (Writes without a body, which end or
    delete something, are not made: the walk's other cases share these objects.)"""
    failures = []
    for req in _requests(gw.s.app.openapi()):
        if req.method not in WRITES or req.body is None or not req.naming():
            continue
        answers = []
        for role in ("admin", "ingest"):
            r, _ = await _send(gw, req, gw.keys[(role, "all")], gw.objects["SIM-003"])
            answers.append(f"{role}: {r.status_code} {r.text[:200]}")
            if r.status_code < 300:
                break
        else:
            failures.append(f"{req}: " + "; ".join(answers))
    assert not failures, "\n".join(failures)


# -- the websocket -----------------------------------------------------------------------------


def _ws_messages(other: str) -> dict[ClientMessage, list[dict[str, Any]]]:
    """What the walk sends of each message type (`auth` opens a connection without other
    credentials), naming the other depot's vehicle every way there is."""
    return {
        ClientMessage.AUTH: [{"type": ClientMessage.AUTH, "key": "{key}"}],
        ClientMessage.SUBSCRIBE: [
            {"type": ClientMessage.SUBSCRIBE, "vehicles": [other]},
            {"type": ClientMessage.SUBSCRIBE, "vehicles": [other, NOPE]},
            {"type": ClientMessage.SUBSCRIBE, "vehicles": other},
            {"type": ClientMessage.SUBSCRIBE, "vehicles": "*"},
            {"type": ClientMessage.SUBSCRIBE, "vehicles": ["*"]},
            {"type": ClientMessage.SUBSCRIBE},
        ],
        ClientMessage.UNSUBSCRIBE: [
            {"type": ClientMessage.UNSUBSCRIBE, "vehicles": [other]},
            {"type": ClientMessage.UNSUBSCRIBE, "vehicles": "*"},
        ],
    }


def _publish_all(gw: Gateway) -> None:
    """A live event of every vehicle, in the scope or not (and one that does not exist)."""
    hub = gw.s.rt.ingest.hub
    for vid in (*DEPOTS, NOPE):
        hub.publish(Event(LIVE, UnitRef(vid, f"{vid}/sim", 30), time.time(), {"slot": "x"}))


async def _walk_websocket(gw: Gateway, role: str, scope: str) -> None:
    """Every way to open the websocket and every message type a client sends, naming the
    other depot's vehicle every way: nothing of it arrives (an ingest key is refused, 4401)."""
    key = gw.keys[(role, scope)]
    other = SCOPES[scope][1]
    mine = sorted(IN_SCOPE[scope])[0]
    others = set(DEPOTS) - IN_SCOPE[scope]
    messages = _ws_messages(other)
    assert set(messages) == set(ClientMessage), "teach the walk the new message types"
    base = f"ws://127.0.0.1:{gw.port}/api/v1/ws"
    header = {"Authorization": f"Bearer {key}"}
    # Every way in: the key as a header with the other vehicle, `*` or nothing asked for in
    # the query string, and the key as an `auth` first message.
    openings: list[tuple[str, dict[str, str], list[dict[str, Any]]]] = [
        (f"{base}?vehicles={other},{mine}", header, []),
        (f"{base}?vehicles=*", header, []),
        (f"{base}?vehicles={other}", header, []),
        (base, {}, _fill(messages[ClientMessage.AUTH], {"{key}": key})),
    ]
    seen: list[str] = []
    for url, headers, first in openings:
        async with websockets.connect(url, additional_headers=headers) as ws:
            for msg in first:
                await ws.send(orjson.dumps(msg).decode())
            if role == "ingest":  # reads nothing: refused like no key
                with pytest.raises(websockets.ConnectionClosed) as closed:
                    while True:
                        async with asyncio.timeout(15):
                            seen.append(str(await ws.recv()))
                assert closed.value.rcvd is not None and closed.value.rcvd.code == 4401
                continue
            for kind in ClientMessage:
                if kind == ClientMessage.AUTH:
                    continue  # a first message: sent above, on its own connection
                for msg in messages[kind]:
                    await ws.send(orjson.dumps(msg).decode())
                    seen.extend(orjson.dumps(m).decode() for m in await ws_sync(ws))
            # Subscribed to all again: events of every vehicle published, then one of the
            # key's own marked; the hub is FIFO, so the other depot's would come before it.
            await ws.send(orjson.dumps({"type": "subscribe", "vehicles": "*"}).decode())
            seen.extend(orjson.dumps(m).decode() for m in await ws_sync(ws))
            mark = f"mark-{time.monotonic_ns()}"
            _publish_all(gw)
            gw.s.rt.ingest.hub.publish(
                Event(LIVE, UnitRef(mine, f"{mine}/sim", 30), time.time(), {"slot": mark})
            )
            got = await ws_until(ws, lambda m, mark=mark: m.get("data", {}).get("slot") == mark)
            seen.extend(orjson.dumps(m).decode() for m in got)
    assert seen, "the walk received nothing"
    leaks = [(m[:200], found) for m in seen if (found := _leaks(m, others, {}))]
    assert not leaks, leaks


def _routes_without_vehicle_scope(app: Any) -> list[str]:
    """Every operation of `app.openapi()` whose path names a vehicle (`{vehicle_id}`) and whose
    route does not resolve it through an `in_scope` dependency."""
    from fastapi.routing import iter_route_contexts

    from eqgw.security.auth import VEHICLE_SCOPE_DEPENDENCIES

    def calls(dependant: Any) -> set[Any]:
        found = {dependant.call}
        for sub in dependant.dependencies:
            found |= calls(sub)
        return found

    # Each route as included (prefix and the router's own dependencies applied).
    routes = {
        (m, r.path): r for r in iter_route_contexts(app.router.routes) for m in r.methods or ()
    }
    missing = []
    for path, ops in app.openapi()["paths"].items():
        if "{vehicle_id}" not in path:
            continue
        for method in ops:
            route = routes[(method.upper(), path)]
            if not calls(route.dependant) & VEHICLE_SCOPE_DEPENDENCIES:
                missing.append(f"{method.upper()} {path}")
    return missing


async def test_every_vehicle_route_resolves_its_vehicle_in_scope(
    tmp_path: Path,
) -> None:
    """One dependency resolves a route's vehicle within the caller's scope; a route that names a
    vehicle without it fails here (the checker itself is shown to find one)."""
    from eqgw.config import Settings
    from eqgw.main import create_app

    app = create_app(Settings(database_url=f"sqlite:///{tmp_path / 'eqgw.db'}"))
    vehicle_paths = [p for p in app.openapi()["paths"] if "{vehicle_id}" in p]
    assert len(vehicle_paths) >= 7, vehicle_paths
    assert _routes_without_vehicle_scope(app) == []

    bad = create_app(Settings(database_url=f"sqlite:///{tmp_path / 'bad.db'}"))

    @bad.get("/api/v1/vehicles/{vehicle_id}/unchecked")
    async def unchecked(vehicle_id: str, who: Viewer) -> dict[str, str]:
        return {"id": vehicle_id}

    bad.openapi_schema = None
    assert _routes_without_vehicle_scope(bad) == ["GET /api/v1/vehicles/{vehicle_id}/unchecked"]
