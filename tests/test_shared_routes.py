"""The apps a process makes share the routes of the API (eqgw.main.shared_routes): FastAPI
builds an included router's routes on the first request through it, so each app including
the routers anew built them all again (0.1 s of CPU an app). Shared, each app still answers
for itself: its own database, its own keys."""

from __future__ import annotations

from pathlib import Path

import httpx
from fastapi import APIRouter

from eqgw.config import Settings
from eqgw.main import ROUTERS, create_app, shared_routes
from eqgw.web.settings import ApiSettings
from tests.api_helpers import lifespan


def test_no_router_has_a_lifespan_the_apps_would_miss() -> None:
    """Shared, the routers are not included into each app, so a lifespan or startup handler
    of a router's own would never run: what a subsystem starts is a part of the gateway's
    lifespan (eqgw.main.lifespan) instead."""
    default = type(APIRouter().lifespan_context)
    for router, prefix in ROUTERS:
        assert type(router.lifespan_context) is default, (prefix, router.lifespan_context)
        assert not router.on_startup and not router.on_shutdown, prefix


def test_two_apps_share_the_api_routes(tmp_path: Path) -> None:
    apps = [
        create_app(Settings(database_url=f"sqlite:///{tmp_path / f'{n}.db'}"), api=ApiSettings())
        for n in ("a", "b")
    ]
    routes = [{id(r) for r in app.routes} for app in apps]
    shared = {id(r) for r in shared_routes()}
    assert len(shared) == len(ROUTERS)
    assert shared <= routes[0] and shared <= routes[1]
    # What each app adds of its own (the dashboard's page, the docs) stays its own.
    assert routes[0] - shared and not (routes[0] - shared) & (routes[1] - shared)


async def test_each_app_answers_with_its_own_database_and_keys(tmp_path: Path) -> None:
    keys: dict[str, list[str]] = {"a": [], "b": []}
    apps = {
        n: create_app(
            Settings(database_url=f"sqlite:///{tmp_path / f'{n}.db'}"),
            api=ApiSettings(),
            on_first_key=keys[n].append,
        )
        for n in keys
    }
    async with lifespan(apps["a"]), lifespan(apps["b"]):
        for n, app in apps.items():
            other = "b" if n == "a" else "a"
            transport = httpx.ASGITransport(app=app)
            async with httpx.AsyncClient(transport=transport, base_url="http://t") as client:
                mine = {"Authorization": f"Bearer {keys[n][0]}"}
                r = await client.post(
                    "/api/v1/keys", json={"name": f"only-{n}", "role": "viewer"}, headers=mine
                )
                assert r.status_code == 201, r.text
                r = await client.get("/api/v1/keys", headers=mine)
                assert r.status_code == 200, r.text
                names = {k["name"] for k in r.json()}
                assert f"only-{n}" in names and f"only-{other}" not in names
                theirs = {"Authorization": f"Bearer {keys[other][0]}"}
                assert (await client.get("/api/v1/keys", headers=theirs)).status_code == 401
