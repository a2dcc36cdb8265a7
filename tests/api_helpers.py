"""Shared pieces of the API tests: a served app with an in-process simulated fleet."""

from __future__ import annotations

import asyncio
import gc
import time
from collections.abc import AsyncIterator, Awaitable, Callable, Iterator
from contextlib import asynccontextmanager, contextmanager
from dataclasses import dataclass
from typing import Any

import httpx
from fastapi import FastAPI

from eqgw.api.lifespan import collector_managed_by_host
from eqgw.config import Settings
from eqgw.main import create_app
from eqgw.sim.clock import RealtimeClock
from eqgw.sim.fleet import SimulatedFleet
from eqgw.sim.vehicle import VehicleSpec
from eqgw.web.runtime import Runtime
from eqgw.web.settings import ApiSettings


@dataclass
class Served:
    """A running app, its simulated fleet, an admin key and a client."""

    app: FastAPI
    sim: SimulatedFleet
    admin_key: str
    client: httpx.AsyncClient

    @property
    def rt(self) -> Runtime:
        rt: Runtime = self.app.state.rt
        return rt

    def auth(self, key: str | None = None) -> dict[str, str]:
        return {"Authorization": f"Bearer {key or self.admin_key}"}

    async def key(self, role: str, name: str | None = None) -> str:
        r = await self.client.post(
            "/api/v1/keys", json={"name": name or role, "role": role}, headers=self.auth()
        )
        assert r.status_code == 201, r.text
        key: str = r.json()["key"]
        return key


async def wait_for(
    cond: Callable[[], Awaitable[Any]], timeout: float = 30.0, what: str = "condition"
) -> Any:
    """Poll `cond` until it returns something truthy (generous timeouts: shared cores)."""
    deadline = time.monotonic() + timeout
    while True:
        value = await cond()
        if value:
            return value
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for {what}")
        await asyncio.sleep(0.05)


@contextmanager
def heap_frozen() -> Iterator[None]:
    """The test process's heap out of the collector's sight while a gateway runs in this
    process. A test process's heap is the test run's (every test module, Hypothesis, the
    browser driver: 300,000+ objects); the run freezes it once its tests are collected
    (tests/conftest.py), so a collection walks only what came later, and a gateway that finds
    the heap frozen leaves the collector alone (eqgw.api.lifespan.serving: it neither
    collects at its start nor thaws at its end). Where something thawed it since (a test of
    that: it says the run no longer manages the collector), it is collected and frozen again
    here."""
    if not collector_managed_by_host() and gc.get_freeze_count() == 0:
        gc.collect()
        gc.freeze()
    yield


@asynccontextmanager
async def lifespan(app: FastAPI) -> AsyncIterator[None]:
    """`app`'s lifespan run in this process, the test process's heap frozen (`heap_frozen`)."""
    with heap_frozen():
        async with app.router.lifespan_context(app):
            yield


@asynccontextmanager
async def served(
    db_url: str,
    vehicles: int | list[VehicleSpec] = 3,
    speed: float = 4.0,
    *,
    config: dict[str, Any] | None = None,
    admin_key: str | None = None,
    background_traffic: bool = False,
    **api: Any,
) -> AsyncIterator[Served]:
    """The app with a simulated fleet (time `speed`x) running its lifespan, and a client:
    `vehicles` generated ones, or these (`config`: more gateway settings; `admin_key`: the
    key of a database used before, which prints none; the rest: API settings)."""
    sim = SimulatedFleet(
        vehicles, seed=1, clock=RealtimeClock(speed), background_traffic=background_traffic
    )
    # Every unit of every simulated vehicle (a generated fleet's SIM-003 has two).
    expected = sum(len(v.spec.units) for v in sim.vehicles.values())
    keys: list[str] = []
    app = create_app(
        Settings(database_url=db_url, **(config or {})),
        api=ApiSettings(**api),
        sim=sim,
        on_first_key=keys.append,
    )
    async with lifespan(app):
        transport = httpx.ASGITransport(app=app)
        async with httpx.AsyncClient(transport=transport, base_url="http://test") as client:
            s = Served(app, sim, admin_key or keys[0], client)

            async def online() -> bool:
                units = s.rt.ingest.live.units.values()
                return len(units) >= expected and all(u.status_flags for u in units)

            await wait_for(online, what="every simulated unit online")
            yield s


@asynccontextmanager
async def uvicorn_serving(app: FastAPI) -> AsyncIterator[int]:
    """`app` (its lifespan already running) served by uvicorn on a free port, for clients
    that need a real socket (websockets); yields the port."""
    import uvicorn

    from tests.proc_helpers import free_port

    port = free_port()
    server = uvicorn.Server(
        uvicorn.Config(
            app,
            host="127.0.0.1",
            port=port,
            log_level="warning",
            ws="websockets-sansio",
            lifespan="off",
        )
    )
    task = asyncio.create_task(server.serve())
    try:
        await wait_for(lambda: asyncio.sleep(0, server.started), what="uvicorn")
        yield port
    finally:
        server.should_exit = True
        async with asyncio.timeout(10):
            await task


async def ws_until(
    ws: Any, pred: Callable[[dict[str, Any]], bool], timeout: float = 15.0
) -> list[dict[str, Any]]:
    """A websocket's messages up to and including the first that satisfies `pred`; fails
    (AssertionError) when none came within `timeout` s or the socket closed before."""
    import orjson

    deadline = time.monotonic() + timeout
    seen: list[dict[str, Any]] = []
    while True:
        left = deadline - time.monotonic()
        if left <= 0:
            raise AssertionError(f"not received in {timeout} s; got {[m['type'] for m in seen]}")
        try:
            async with asyncio.timeout(left):
                raw = await ws.recv()
        except TimeoutError:
            continue
        seen.append(orjson.loads(raw))
        if pred(seen[-1]):
            return seen


async def ws_sync(ws: Any, timeout: float = 15.0) -> list[dict[str, Any]]:
    """The messages a websocket got until the server handled every message sent before:
    it answers an unknown type with an error, in order, and changes nothing else. Fails
    when that answer never comes."""
    import orjson

    mark = f"sync-{time.monotonic_ns()}"
    await ws.send(orjson.dumps({"type": mark}).decode())
    seen = await ws_until(
        ws, lambda m: m["type"] == "error" and mark in m.get("reason", ""), timeout
    )
    return seen[:-1]
