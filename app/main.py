"""The application factory: `create_app(settings)` and the lifespan that owns every resource.

The lifespan is a list of parts, one a subsystem, each an async context manager in its own
package (`eqgw.<subsystem>.lifespan`, or the subsystem's own class): entered in order, left
in the reverse order, each bounding its own stop. A new subsystem is one more line.
"""

from __future__ import annotations

import asyncio
import functools
import logging
from collections.abc import AsyncIterator, Callable
from contextlib import AsyncExitStack, asynccontextmanager
from dataclasses import dataclass
from typing import TYPE_CHECKING

from fastapi import APIRouter, FastAPI, Request
from fastapi.responses import FileResponse, Response
from fastapi.staticfiles import StaticFiles
from starlette.routing import BaseRoute

from eqgw import version
from eqgw.alerts import endpoints as alerts
from eqgw.alerts.lifespan import alerting
from eqgw.api import exports, health, ws
from eqgw.api.lifespan import runtime, serving
from eqgw.api.metrics import LatencyMiddleware, Metrics, documented_paths
from eqgw.api.openapi import install_docs, operation_id
from eqgw.bus.config import BusConfig
from eqgw.bus.reader import BusReader
from eqgw.cluster.lifespan import cluster_node, startup_lock
from eqgw.cluster.node import cluster_enabled
from eqgw.cluster.settings import ClusterSettings
from eqgw.commands import endpoints as commands
from eqgw.commands.lifespan import commanding
from eqgw.config import Settings, VehicleConfig
from eqgw.fleet import endpoints as fleet
from eqgw.fleet import management as fleet_management
from eqgw.fleet import raw_export
from eqgw.fleet.lifespan import following, seeded_fleet
from eqgw.forward import endpoints as ingest
from eqgw.forward.endpoints import forwarding
from eqgw.ingest.lifespan import ingesting
from eqgw.notify import endpoints as webhooks
from eqgw.notify.lifespan import delivering, telemetry
from eqgw.resources import static_dir
from eqgw.security import endpoints as admin
from eqgw.security import me as session
from eqgw.security import oidc
from eqgw.security import sessions as browser_session
from eqgw.security.auth import audit_invalid_write
from eqgw.security.guard import RequestGuard
from eqgw.security.lifespan import first_admin, key_upkeep
from eqgw.store.lifespan import ShutdownClock, database
from eqgw.store.migrate import upgrade_engine
from eqgw.store.partition_keeper import PartitionKeeper
from eqgw.supervisor import FatalError, Supervisor
from eqgw.web.errors import install_error_handlers
from eqgw.web.responses import JsonResponse
from eqgw.web.settings import ApiSettings

if TYPE_CHECKING:
    from eqgw.cluster.node import ClusterNode
    from eqgw.sim.fleet import SimulatedFleet

log = logging.getLogger(__name__)
# How long uvicorn waits for open requests and websockets when asked to stop.
SERVER_SHUTDOWN_S = 1

API_PREFIX = "/api/v1"
STATIC_DIR = static_dir()
# The routers, in the order their routes are matched.
ROUTERS: list[tuple[APIRouter, str]] = [
    (health.router, ""),
    (fleet.router, API_PREFIX),
    (fleet_management.router, API_PREFIX),
    (commands.router, API_PREFIX),
    (admin.router, API_PREFIX),
    (alerts.router, API_PREFIX),
    (session.router, API_PREFIX),
    (browser_session.router, API_PREFIX),
    (oidc.router, ""),
    (ingest.router, API_PREFIX),
    (ws.router, ""),
    (webhooks.router, API_PREFIX),
    (exports.router, API_PREFIX),
    (raw_export.router, API_PREFIX),
]


@functools.cache
def shared_routes() -> tuple[BaseRoute, ...]:
    """The routes of ROUTERS, included once per process and shared by every app it makes.

    FastAPI builds an included router's routes (each one's dependencies, parameters and
    response models analysed again, with their validators) for the router that includes
    them, on the first request routed through it. Included by each app, that was done again
    for every app a process makes (0.1 s of CPU each, in the warm-up): a program that makes
    many (a test suite) paid it each time. Included here by a router with the app's own
    defaults, they are built once; the apps share them as they share the routers, whose
    handlers find everything of their app through the request. A router's own lifespan
    would not reach the apps: none has one (what a subsystem starts is a part of `lifespan`;
    tests/test_shared_routes.py checks)."""
    router = APIRouter(
        default_response_class=JsonResponse, generate_unique_id_function=operation_id
    )
    for included, prefix in ROUTERS:
        router.include_router(included, prefix=prefix)
    return tuple(router.routes)


def simulated_settings(settings: Settings, sim: SimulatedFleet) -> Settings:
    """The settings plus one vehicle (unless configured: its depot is kept) and one virtual
    bus per simulated vehicle."""
    vehicles = list(settings.vehicles)
    buses = list(settings.buses)
    configured = {v.id for v in vehicles}
    for name, vehicle in sim.vehicles.items():
        if name not in configured:
            vehicles.append(VehicleConfig(id=name, name=name, depot="simulated"))
        bus = BusConfig(
            name=f"{name}/sim",
            vehicle_id=name,
            interface="virtual",
            channel=vehicle.channel,
            bitrate=None,
            equalizer_sas=[u.sa for u in vehicle.spec.units],
        )
        buses.append(settings.apply_address_claim(bus))
    return settings.model_copy(update={"vehicles": vehicles, "buses": buses})


@dataclass(frozen=True, slots=True)
class Gateway:
    """What `create_app` fixed for its lifespan: the settings (`fleet_file` as given, `settings`
    the gateway's own copy, with the simulated fleet's), and the caller's hooks."""

    settings: Settings
    fleet_file: Settings
    api: ApiSettings
    cluster: ClusterSettings
    sim: SimulatedFleet | None
    metrics: Metrics
    on_first_key: Callable[[str], None] | None
    on_login_code: Callable[[str], None] | None
    on_ready: Callable[[], None] | None
    on_fatal: Callable[[FatalError], None] | None
    on_stopped: Callable[[int], None] | None

    @property
    def clustered(self) -> bool:
        """Several gateways share the buses (PostgreSQL, `cluster.mode` auto, no simulation)."""
        return self.sim is None and cluster_enabled(self.cluster, self.settings.database_url)

    @property
    def public_url(self) -> str:
        return self.api.public_url or f"http://{self.api.host}:{self.api.port}"


@asynccontextmanager
async def lifespan(g: Gateway, app: FastAPI) -> AsyncIterator[None]:
    """Each subsystem's part, in the order they start; they stop in the reverse order, each
    bounded, all within `api.shutdown_timeout_s` (after uvicorn's own part)."""
    settings, api, metrics, clustered = g.settings, g.api, g.metrics, g.clustered
    shutdown = ShutdownClock(api.shutdown_timeout_s - SERVER_SHUTDOWN_S - 0.5)
    async with AsyncExitStack() as stack:
        part = stack.enter_async_context
        engine = await part(database(settings.database_url, settings.db))
        starting = await part(startup_lock(engine))
        await asyncio.to_thread(upgrade_engine, engine)
        await first_admin(engine, api, g.on_first_key, g.on_login_code)
        fleet = await seeded_fleet(engine, settings, g.fleet_file)
        if g.sim is not None:
            await part(g.sim)
        tasks = app.state.tasks = await part(Supervisor(on_fatal=g.on_fatal))
        # PostgreSQL's time partitions, made before the ingest writes into them.
        await part(PartitionKeeper(engine, settings.retention, tasks))
        # Clustered, buses are read once their lease is held (cluster_node below).
        readers = [] if clustered else [BusReader(cfg) for cfg in settings.buses]
        ingest = await part(
            ingesting(
                settings,
                engine,
                readers,
                tasks,
                paused=clustered,
                shutdown=shutdown,
                on_stopped=g.on_stopped,
            )
        )
        commands = await part(
            commanding(
                settings,
                api,
                engine,
                ingest,
                readers,
                tasks,
                routable=lambda bus: _routable(app, bus),
            )
        )
        app.state.delivery = await part(
            delivering(engine, settings, g.public_url, metrics.registry)
        )
        app.state.alerts = await part(alerting(settings, engine, ingest))
        node = app.state.cluster = await part(
            cluster_node(clustered, g.cluster, settings.buses, ingest, commands, tasks)
        )
        rt = app.state.rt = runtime(
            settings, api, engine, ingest, commands, fleet.depots, metrics, g.sim
        )
        rt.fleet_sync = await part(
            following(engine, fleet, ingest, commands, node, tasks, on_change=rt.fleet_changed)
        )
        app.state.telemetry = await part(
            telemetry(settings, g.cluster, ingest, tasks, metrics.registry)
        )
        await part(key_upkeep(rt, tasks))
        await part(tasks.running("event loop lag probe", metrics.watch_loop))
        await starting.release()
        await part(serving(app, g.on_ready))
        await part(forwarding(app))
        yield
        # uvicorn's own part (closing connections) came first, bounded by the CLI.
        shutdown.begin()


def create_app(
    settings: Settings,
    *,
    api: ApiSettings | None = None,
    sim: SimulatedFleet | None = None,
    cluster: ClusterSettings | None = None,
    on_first_key: Callable[[str], None] | None = None,
    on_login_code: Callable[[str], None] | None = None,
    on_ready: Callable[[], None] | None = None,
    on_fatal: Callable[[FatalError], None] | None = None,
    on_stopped: Callable[[int], None] | None = None,
) -> FastAPI:
    """The gateway as an ASGI app; the lifespan migrates, ingests, delivers commands and serves.

    With `sim`, the simulated fleet's vehicles and virtual buses join the settings and the
    lifespan starts and stops the fleet. `on_first_key` receives the admin key created on a
    database that never had one (the CLI prints it, once, for the API), `on_login_code` then a
    one-time login code of that key for the dashboard (the CLI prints its link); `on_ready`
    is called once everything has started; `on_fatal` when a background task meets a fault
    that will not heal (the CLI ends the process non-zero); `on_stopped` with the rows the
    ingest's final flush could not write (0 normally) once it ran. On PostgreSQL
    (`cluster.mode` auto) the gateway reads only the buses it holds a lease on, several
    gateways sharing the configured buses (app/cluster); a simulated fleet is private to its
    process, not shared.
    """
    api = api or ApiSettings()
    # The gateway's own copy: its fleet lists are replaced as the database's fleet changes.
    fleet_file = settings.model_copy()
    settings = simulated_settings(fleet_file, sim) if sim is not None else settings.model_copy()
    metrics = Metrics()
    g = Gateway(
        settings,
        fleet_file,
        api,
        cluster or ClusterSettings(),
        sim,
        metrics,
        on_first_key,
        on_login_code,
        on_ready,
        on_fatal,
        on_stopped,
    )
    app = FastAPI(
        title="eqgw",
        summary="Fleet gateway for Vanner VANN-Guard battery equalizers",
        version=version(),
        lifespan=functools.partial(lifespan, g),
        default_response_class=JsonResponse,
        generate_unique_id_function=operation_id,
        # Swagger UI from the gateway's own files (install_docs); no ReDoc, which needs a CDN.
        # The interactive docs and the schema can be switched off (EQGW_API_DOCS=false).
        docs_url=None,
        redoc_url=None,
        openapi_url="/openapi.json" if api.docs else None,
    )
    app.state.metrics = metrics
    app.state.settings = settings
    app.state.open_websockets = ws.OpenWebsockets()
    app.state.warm_up_s = None  # seconds the warm-up took, once done (the lifespan)
    app.state.telemetry = None  # the MQTT telemetry publisher, when enabled (the lifespan)
    app.state.cluster = None  # the cluster node, when clustered (the lifespan)
    # Single sign-on (its routes answer 404 while oidc.issuer is unset).
    app.state.oidc = None
    if settings.oidc.enabled:
        from eqgw.security.oidc_provider import OidcProvider

        app.state.oidc = OidcProvider(settings.oidc)
    app.state.on_invalid_write = audit_invalid_write
    install_error_handlers(app)
    app.add_middleware(LatencyMiddleware, metrics=metrics)
    app.add_middleware(RequestGuard, api=api)
    # The routers' routes as one process-wide list (shared_routes), not included anew here.
    app.router.routes.extend(shared_routes())
    metrics.routes.load(documented_paths(ROUTERS))
    _mount_dashboard(app)
    if api.docs:
        install_docs(app)
    return app


def _routable(app: FastAPI, bus: str) -> bool:
    """Whether some gateway of the cluster delivers commands on `bus` (none: not clustered)."""
    node: ClusterNode | None = app.state.cluster
    return node is not None and node.routable(bus)


def _mount_dashboard(app: FastAPI) -> None:
    """The browser dashboard: `/` is its page, `/static/...` its files (absent dir: API only)."""
    if not (STATIC_DIR / "index.html").is_file():
        log.warning("no dashboard: %s/index.html is missing", STATIC_DIR)
        return
    index = STATIC_DIR / "index.html"

    @app.get("/", include_in_schema=False)
    async def dashboard(request: Request) -> Response:
        # A key in the address logs no one in; the address loses it (login links carry a
        # one-time code in the fragment instead, which the page exchanges).
        stripped = browser_session.key_in_url(request)
        if stripped is not None:
            return stripped
        # Revalidated on every load so a new deploy's page is never served stale.
        return FileResponse(index, headers={"Cache-Control": "no-cache"})

    app.mount("/static", StaticFiles(directory=STATIC_DIR), name="static")
