"""The application factory: `create_app(settings)` and the lifespan that owns every resource."""

from __future__ import annotations

import asyncio
import contextlib
import gc
import logging
from collections.abc import AsyncIterator, Callable
from contextlib import asynccontextmanager
from pathlib import Path
from typing import TYPE_CHECKING

from fastapi import FastAPI
from fastapi.responses import FileResponse
from fastapi.staticfiles import StaticFiles

from app.api import admin, alerts, commands, fleet, health, ingest, session, ws
from app.api.auth import KeyAuthenticator, ensure_first_admin
from app.api.deps import RateLimiter, Runtime, audit_invalid_write
from app.api.errors import install_error_handlers
from app.api.metrics import LatencyMiddleware, Metrics
from app.api.responses import JsonResponse
from app.api.settings import ApiSettings
from app.bus.config import BusConfig
from app.cluster.leases import StartupLock
from app.cluster.node import ClusterNode, cluster_enabled
from app.cluster.settings import ClusterSettings
from app.config import Settings, VehicleConfig
from app.store.engine import create_engine
from app.store.history_cache import HistoryCache
from app.store.migrate import upgrade_engine

if TYPE_CHECKING:
    from app.sim.fleet import SimulatedFleet

log = logging.getLogger(__name__)

# The collector's generation thresholds while the gateway serves (see the lifespan).
GC_THRESHOLDS = (10_000, 20, 20)

API_PREFIX = "/api/v1"
STATIC_DIR = Path(__file__).resolve().parent.parent / "static"
KEY_FLUSH_S = 10.0


def simulated_settings(settings: Settings, sim: SimulatedFleet) -> Settings:
    """The settings plus one vehicle and one virtual bus per simulated vehicle."""
    vehicles = list(settings.vehicles)
    buses = list(settings.buses)
    for name, vehicle in sim.vehicles.items():
        vehicles.append(VehicleConfig(id=name, name=name, depot="simulated"))
        buses.append(
            BusConfig(
                name=f"{name}/sim",
                vehicle_id=name,
                interface="virtual",
                channel=vehicle.channel,
                bitrate=None,
                equalizer_sas=[u.sa for u in vehicle.spec.units],
            )
        )
    return settings.model_copy(update={"vehicles": vehicles, "buses": buses})


def create_app(
    settings: Settings,
    *,
    api: ApiSettings | None = None,
    sim: SimulatedFleet | None = None,
    cluster: ClusterSettings | None = None,
    on_first_key: Callable[[str], None] | None = None,
    on_ready: Callable[[], None] | None = None,
) -> FastAPI:
    """The gateway as an ASGI app; the lifespan migrates, ingests, delivers commands and serves.

    With `sim`, the simulated fleet's vehicles and virtual buses join the settings and the
    lifespan starts and stops the fleet. `on_first_key` receives the admin key created on a
    database that never had one (the CLI prints it, once); `on_ready` is called once
    everything has started. On PostgreSQL (`cluster.mode`
    auto) the gateway reads only the buses it holds a lease on, several gateways sharing the
    configured buses (app/cluster); a simulated fleet is private to its process, not shared.
    """
    api = api or ApiSettings()
    cluster = cluster or ClusterSettings()
    clustered = sim is None and cluster_enabled(cluster, settings.database_url)
    if sim is not None:
        settings = simulated_settings(settings, sim)
    metrics = Metrics()

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        from app.bus.reader import BusReader
        from app.bus.writer import BusWriter
        from app.commands.identify import UnitIdentifier
        from app.commands.service import CommandService
        from app.ingest.service import IngestService

        engine = create_engine(settings.database_url)
        async with contextlib.AsyncExitStack() as stack:
            stack.callback(engine.dispose)
            # Gateways starting together on one PostgreSQL start one at a time.
            startup = StartupLock(engine)
            await asyncio.to_thread(startup.acquire)
            stack.callback(startup.release)
            await asyncio.to_thread(upgrade_engine, engine)
            first_key = await asyncio.to_thread(ensure_first_admin, engine)
            if first_key is not None and on_first_key is not None:
                on_first_key(first_key)
            if sim is not None:
                await sim.start()
                stack.push_async_callback(sim.stop)
            # Clustered, buses are read once their lease is held (ClusterNode below).
            readers = [] if clustered else [BusReader(cfg) for cfg in settings.buses]
            ingest = IngestService(settings, engine=engine, sources=readers)
            if clustered:
                ingest.pause_all()
            await ingest.start(migrate=False)
            node: ClusterNode | None = None
            stack.push_async_callback(ingest.stop)
            service = CommandService(
                engine,
                ingest.live,
                {r.name: BusWriter(r) for r in readers},
                {b.name: b for b in settings.buses},
                lambda: {v.id for v in settings.vehicles},
                api,
                routable=lambda bus: node is not None and node.routable(bus),
            )
            await service.start()
            stack.push_async_callback(service.stop)
            identifier = UnitIdentifier(ingest.hub, service)
            await identifier.start()
            stack.push_async_callback(identifier.stop)
            stack.callback(service.hub.close)
            from app.alerts.engine import start_alert_engine

            alert_engine = await start_alert_engine(settings, engine, ingest)
            if alert_engine is not None:
                stack.push_async_callback(alert_engine.stop)
            app.state.alerts = alert_engine
            if clustered:
                node = ClusterNode(cluster, settings.database_url, settings.buses, ingest, service)
                await node.start()
                stack.push_async_callback(node.stop)
            app.state.cluster = node
            keys = KeyAuthenticator(engine, api.key_cache_s)
            rt = Runtime(
                settings=settings,
                api=api,
                engine=engine,
                ingest=ingest,
                commands=service,
                keys=keys,
                limiter=RateLimiter(api.write_rate, api.write_window_s),
                fleet=sim,
                history=HistoryCache(max_buckets=api.history_cache_buckets),
            )
            metrics.attach(rt)
            app.state.rt = rt
            from app.alerts.delivery import AlertDelivery

            delivery = AlertDelivery(
                engine, settings, api.public_url or f"http://{api.host}:{api.port}"
            )
            await delivery.start(metrics.registry)
            stack.push_async_callback(delivery.stop)
            app.state.delivery = delivery
            flusher = asyncio.create_task(_flush_keys(keys), name="api key last-used")
            stack.push_async_callback(_cancel, flusher)
            probe = asyncio.create_task(metrics.watch_loop(), name="event loop lag probe")
            stack.push_async_callback(_cancel, probe)
            stack.callback(keys.flush_last_used)
            await asyncio.to_thread(startup.release)
            # What startup built (modules, the app, the schema, the fleet) lives as long as
            # the process: out of the collector's sight, a full collection walks only what
            # came later, a few milliseconds instead of 100+ ms with every thread stopped
            # (each such pause was a latency spike of every request, frame and websocket).
            # Young collections every 10,000 allocations instead of 700: requests and frames
            # allocate fast and almost all of it dies young, freed by reference counting.
            thresholds = gc.get_threshold()
            gc.collect()
            gc.freeze()
            gc.set_threshold(*GC_THRESHOLDS)
            if on_ready is not None:
                on_ready()
            yield
            gc.set_threshold(*thresholds)
            gc.unfreeze()

    app = FastAPI(
        title="eqgw",
        summary="Fleet gateway for Vanner VANN-Guard battery equalizers",
        version="0.1.0",
        lifespan=lifespan,
        default_response_class=JsonResponse,
    )
    app.state.metrics = metrics
    app.state.settings = settings
    install_error_handlers(app)
    app.state.on_invalid_write = audit_invalid_write
    app.add_middleware(LatencyMiddleware, metrics=metrics)
    app.include_router(health.router)
    app.include_router(fleet.router, prefix=API_PREFIX)
    app.include_router(commands.router, prefix=API_PREFIX)
    app.include_router(admin.router, prefix=API_PREFIX)
    app.include_router(alerts.router, prefix=API_PREFIX)
    app.include_router(session.router, prefix=API_PREFIX)
    app.include_router(ingest.router, prefix=API_PREFIX)
    app.include_router(ws.router)
    from app.api import webhooks

    app.include_router(webhooks.router, prefix=API_PREFIX)
    _mount_dashboard(app)
    return app


def _mount_dashboard(app: FastAPI) -> None:
    """The browser dashboard: `/` is its page, `/static/...` its files (absent dir: API only)."""
    if not (STATIC_DIR / "index.html").is_file():
        log.warning("no dashboard: %s/index.html is missing", STATIC_DIR)
        return
    index = STATIC_DIR / "index.html"

    @app.get("/", include_in_schema=False)
    async def dashboard() -> FileResponse:
        # Revalidated on every load so a new deploy's page is never served stale.
        return FileResponse(index, headers={"Cache-Control": "no-cache"})

    app.mount("/static", StaticFiles(directory=STATIC_DIR), name="static")


async def _flush_keys(keys: KeyAuthenticator) -> None:
    while True:
        await asyncio.sleep(KEY_FLUSH_S)
        try:
            await asyncio.to_thread(keys.flush_last_used)
        except Exception as exc:  # the database may be away; the times wait for next round
            log.warning("recording key use failed: %s", exc)


async def _cancel(task: asyncio.Task[None]) -> None:
    task.cancel()
    with contextlib.suppress(asyncio.CancelledError):
        await task
