"""The application factory: `create_app(settings)` and the lifespan that owns every resource."""

from __future__ import annotations

import asyncio
import contextlib
import gc
import logging
import time
from collections.abc import AsyncIterator, Callable
from contextlib import asynccontextmanager
from typing import TYPE_CHECKING

from fastapi import FastAPI, Request
from fastapi.responses import FileResponse, Response
from fastapi.staticfiles import StaticFiles

from eqgw import version
from eqgw.alerts import endpoints as alerts
from eqgw.api import health, ws
from eqgw.api.deps import RateLimiter, Runtime, audit_invalid_write
from eqgw.api.errors import install_error_handlers
from eqgw.api.metrics import LatencyMiddleware, Metrics
from eqgw.api.openapi import install_docs, operation_id
from eqgw.api.responses import JsonResponse
from eqgw.api.settings import ApiSettings
from eqgw.api.warmup import warm_up
from eqgw.bus.config import BusConfig
from eqgw.cluster.leases import StartupLock
from eqgw.cluster.node import ClusterNode, cluster_enabled
from eqgw.cluster.settings import ClusterSettings
from eqgw.commands import endpoints as commands
from eqgw.config import Settings, VehicleConfig
from eqgw.fleet import endpoints as fleet
from eqgw.fleet import registry as fleet_registry
from eqgw.fleet.sync import DepotMap, FleetSync, FleetView
from eqgw.forward import endpoints as ingest
from eqgw.resources import static_dir
from eqgw.security import endpoints as admin
from eqgw.security import me as session
from eqgw.security import sessions as browser_session
from eqgw.security.audit import prune_audit
from eqgw.security.guard import RequestGuard
from eqgw.security.keys import KeyAuthenticator, ensure_first_admin
from eqgw.security.limit_repository import prune_write_hits
from eqgw.store.engine import create_engine, database_deadline_scope, end_database_work_by
from eqgw.store.history_cache import HistoryCache
from eqgw.store.migrate import upgrade_engine
from eqgw.store.partition_keeper import PartitionKeeper
from eqgw.supervisor import FatalError, Supervisor, permanent_fault
from eqgw.tasks import cancel_and_wait

if TYPE_CHECKING:
    from sqlalchemy import Engine

    from eqgw.ingest.service import IngestService
    from eqgw.notify.telemetry import TelemetryPublisher
    from eqgw.sim.fleet import SimulatedFleet

log = logging.getLogger(__name__)
# How long uvicorn waits for open requests and websockets when asked to stop.
SERVER_SHUTDOWN_S = 1

# The collector's generation thresholds while the gateway serves (see the lifespan).
GC_THRESHOLDS = (10_000, 20, 20)

# Of the shutdown's time, kept for the ingest's final flush (or its journal) at the end.
SHUTDOWN_WRITER_RESERVE_S = 2.5

API_PREFIX = "/api/v1"
STATIC_DIR = static_dir()
KEY_FLUSH_S = 10.0
AUDIT_PRUNE_S = 3600.0
# Refusals without a key are written at most this often (one row per action each time).
REFUSALS_FLUSH_S = 60.0


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
    cluster = cluster or ClusterSettings()
    clustered = sim is None and cluster_enabled(cluster, settings.database_url)
    # The gateway's own copy: its fleet lists are replaced as the database's fleet changes.
    fleet_file = settings.model_copy()
    settings = simulated_settings(fleet_file, sim) if sim is not None else settings.model_copy()
    metrics = Metrics()

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        from eqgw.bus.reader import BusReader
        from eqgw.bus.writer import BusWriter
        from eqgw.commands.identify import UnitIdentifier
        from eqgw.commands.service import CommandService
        from eqgw.ingest.service import IngestService

        engine = create_engine(settings.database_url, deadlines=settings.db)
        async with contextlib.AsyncExitStack() as stack:
            # The shutdown's database deadline (set after `yield`) is the lifespan's alone:
            # undone when the last resource is closed, so a context that runs a lifespan and
            # goes on (a test, an embedding program) keeps no deadline that has passed.
            stack.enter_context(database_deadline_scope())
            stack.callback(engine.dispose)
            # Gateways starting together on one PostgreSQL start one at a time.
            startup = StartupLock(engine)
            await asyncio.to_thread(startup.acquire)
            stack.callback(startup.release)
            await asyncio.to_thread(upgrade_engine, engine)
            first_key = await asyncio.to_thread(ensure_first_admin, engine)
            if first_key is not None and on_first_key is not None:
                on_first_key(first_key)
            if first_key is not None and on_login_code is not None:
                ttl = api.login_code_ttl_s
                on_login_code(await asyncio.to_thread(_login_code_of, engine, first_key, ttl))
            # The fleet: the database's (the fleet file seeds a database that has none).
            view = FleetView(
                settings,
                [v for v in settings.vehicles if fleet_file.vehicle(v.id) is None],
                settings.buses[len(fleet_file.buses) :],
            )
            seeded = await asyncio.to_thread(
                fleet_registry.seed,
                engine,
                fleet_file.vehicles,
                fleet_file.buses,
                fleet_file.address_claim,
            )
            _say_seeded(seeded)
            settings.vehicles, settings.buses = view.compose(seeded.fleet)
            depots = DepotMap(fleet_registry.depots_of(settings.vehicles))
            if sim is not None:
                await sim.start()
                stack.push_async_callback(sim.stop)
            # Clustered, buses are read once their lease is held (ClusterNode below).
            readers = [] if clustered else [BusReader(cfg) for cfg in settings.buses]
            tasks = Supervisor(on_fatal=on_fatal)
            app.state.tasks = tasks
            stack.push_async_callback(tasks.stop)
            ingest = IngestService(
                settings,
                engine=engine,
                sources=readers,
                supervisor=tasks,
                fleet_from_settings=False,
            )
            if clustered:
                ingest.pause_all()
            await ingest.start(migrate=False)
            node: ClusterNode | None = None
            stopping_by: list[float] = []  # when the shutdown must be over (monotonic)

            async def stop_ingest() -> None:
                # The final flush gets what is left of the shutdown's time, at least 1 s.
                left_s = stopping_by[0] - time.monotonic() if stopping_by else 30.0
                left = await ingest.stop(timeout=max(1.0, left_s))
                if on_stopped is not None:
                    on_stopped(left)

            stack.push_async_callback(stop_ingest)
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
            identifier = UnitIdentifier(ingest.hub, service, supervisor=tasks)
            await identifier.start()
            stack.push_async_callback(identifier.stop)
            stack.callback(service.hub.close)
            from eqgw.alerts.engine import start_alert_engine
            from eqgw.notify.delivery import AlertDelivery

            delivery = AlertDelivery(
                engine, settings, api.public_url or f"http://{api.host}:{api.port}"
            )
            await delivery.prepare()
            alert_engine = await start_alert_engine(settings, engine, ingest)
            if alert_engine is not None:
                stack.push_async_callback(alert_engine.stop)
            app.state.alerts = alert_engine
            if clustered:
                node = ClusterNode(cluster, settings.database_url, settings.buses, ingest, service)
                await node.start()
                stack.push_async_callback(node.stop)
            app.state.cluster = node
            keys = KeyAuthenticator(engine, api.key_cache_s, depots=depots)
            rt = Runtime(
                settings=settings,
                api=api,
                engine=engine,
                ingest=ingest,
                commands=service,
                keys=keys,
                limiter=RateLimiter(api.write_rate, api.write_window_s, engine),
                fleet=sim,
                history=HistoryCache(max_buckets=api.history_cache_buckets),
            )
            metrics.attach(rt)
            app.state.rt = rt
            sync = FleetSync(
                engine,
                view,
                version=seeded.fleet.version,
                ingest=ingest,
                commands=service,
                depots=depots,
                node=node,
                on_change=rt.fleet_changed,
            )
            rt.fleet_sync = sync
            follower = tasks.start("fleet sync", sync.run)
            stack.push_async_callback(cancel_and_wait, follower)
            await delivery.start(metrics.registry)
            stack.push_async_callback(delivery.stop)
            app.state.delivery = delivery
            app.state.telemetry = await _start_telemetry(
                settings, cluster, ingest, tasks, metrics, stack
            )
            await stack.enter_async_context(PartitionKeeper(engine, settings.retention, tasks))
            flusher = tasks.start("api key last-used and audit", lambda: _flush_keys(rt))
            stack.push_async_callback(cancel_and_wait, flusher)
            probe = tasks.start("event loop lag probe", metrics.watch_loop)
            stack.push_async_callback(cancel_and_wait, probe)
            stack.callback(keys.flush_last_used)
            stack.callback(_flush_refusals, rt)
            await asyncio.to_thread(startup.release)
            # Ready only once the API's lazily built parts are built (its first request
            # would take them on, 1-2 s): /readyz cannot answer before this point.
            app.state.warm_up_s = await warm_up(app, metrics)
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
            # uvicorn's own part (closing connections) came first, bounded by the CLI.
            stopping_by.append(time.monotonic() + api.shutdown_timeout_s - SERVER_SHUTDOWN_S - 0.5)
            # A database that stops answering must not hold the stop past its bound: every
            # database call of the shutdown ends in time for the writer to journal its rows.
            end_database_work_by(stopping_by[0] - SHUTDOWN_WRITER_RESERVE_S)
            gc.set_threshold(*thresholds)
            gc.unfreeze()

    app = FastAPI(
        title="eqgw",
        summary="Fleet gateway for Vanner VANN-Guard battery equalizers",
        version=version(),
        lifespan=lifespan,
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
    install_error_handlers(app)
    app.state.on_invalid_write = audit_invalid_write
    app.add_middleware(LatencyMiddleware, metrics=metrics)
    app.add_middleware(RequestGuard, api=api)
    app.include_router(health.router)
    app.include_router(fleet.router, prefix=API_PREFIX)
    from eqgw.fleet import management as fleet_management

    app.include_router(fleet_management.router, prefix=API_PREFIX)
    app.include_router(commands.router, prefix=API_PREFIX)
    app.include_router(admin.router, prefix=API_PREFIX)
    app.include_router(alerts.router, prefix=API_PREFIX)
    app.include_router(session.router, prefix=API_PREFIX)
    app.include_router(browser_session.router, prefix=API_PREFIX)
    from eqgw.security import oidc

    # Single sign-on (its routes answer 404 while oidc.issuer is unset).
    app.state.oidc = oidc.OidcProvider(settings.oidc) if settings.oidc.enabled else None
    app.include_router(oidc.router)
    app.include_router(ingest.router, prefix=API_PREFIX)
    app.include_router(ws.router)
    from eqgw.notify import endpoints as webhooks

    app.include_router(webhooks.router, prefix=API_PREFIX)
    from eqgw.api import exports

    app.include_router(exports.router, prefix=API_PREFIX)
    from eqgw.fleet import raw_export

    app.include_router(raw_export.router, prefix=API_PREFIX)
    _mount_dashboard(app)
    if api.docs:
        install_docs(app)
    return app


def _say_seeded(seeded: fleet_registry.SeedResult) -> None:
    """One line on what the fleet file did at this start."""
    fleet = seeded.fleet
    if seeded.seeded:
        log.info(
            "fleet: the database had no fleet: seeded from the fleet file (%d vehicles, %d "
            "buses); from now on the database holds the fleet",
            len(fleet.vehicles),
            len(fleet.buses),
        )
    elif seeded.differ:
        when = (
            time.strftime("%Y-%m-%d %H:%M", time.localtime(seeded.seeded_at))
            if seeded.seeded_at
            else "?"
        )
        shown = ", ".join(seeded.differ[:5]) + (", ..." if len(seeded.differ) > 5 else "")
        log.warning(
            "fleet: the fleet file's vehicles and buses were not applied: the database holds "
            "the fleet (since %s, from %s; version %d) and %d of the file's differ from it "
            "(%s). Manage vehicles with the API (/api/v1/vehicles) or `eqgw vehicles import`; "
            "remove [[vehicles]] and [[buses]] from the file to silence this",
            when,
            seeded.seeded_from,
            fleet.version,
            len(seeded.differ),
            shown,
        )


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


async def _start_telemetry(
    settings: Settings,
    cluster: ClusterSettings,
    ingest: IngestService,
    tasks: Supervisor,
    metrics: Metrics,
    stack: contextlib.AsyncExitStack,
) -> TelemetryPublisher | None:
    """MQTT telemetry when enabled: connected, its loop supervised, its counters scraped; each
    undone by `stack` (the loop first, then `offline` said and the connection closed)."""
    if not settings.mqtt.telemetry.enabled:
        return None
    from eqgw.notify.telemetry import TelemetryPublisher, gateway_id

    def names(vehicle_id: str) -> tuple[str, str | None]:
        v = settings.vehicle(vehicle_id)
        return (vehicle_id, None) if v is None else (v.display_name, v.depot)

    explicit = cluster.instance_id if "instance_id" in cluster.model_fields_set else None
    telemetry = TelemetryPublisher(
        settings.mqtt,
        gateway_id(settings.mqtt.telemetry.gateway_id, explicit),
        ingest.hub,
        ingest.live,
        owned_buses=lambda: [*ingest.reading(), *ingest.live.attached],
        vehicle_names=names,
        not_reporting_after_s=settings.monitor.not_reporting_after_s,
        queue=settings.hub.subscriber_queue,
    )
    await telemetry.start()
    stack.push_async_callback(telemetry.stop)
    metrics.registry.register(telemetry.collector)
    stack.callback(metrics.registry.unregister, telemetry.collector)
    loop = tasks.start("mqtt telemetry", telemetry.run)
    stack.push_async_callback(cancel_and_wait, loop)
    return telemetry


def _login_code_of(engine: Engine, key: str, ttl_s: float) -> str:
    """A one-time login code of `key` (the first admin's, for the first start's link)."""
    from eqgw.security import repository as q
    from eqgw.security.keys import hash_key
    from eqgw.security.login_codes import create_login_code

    with engine.connect() as conn:
        row = q.key_by_hash(conn, hash_key(key))
    assert row is not None
    # Its own transaction that writes first (SQLite: a read that then writes cannot wait for
    # the write lock; a first write waits its busy timeout).
    with engine.begin() as conn:
        return create_login_code(conn, int(row["id"]), ttl_s)


async def _flush_keys(rt: Runtime) -> None:
    """Every KEY_FLUSH_S, keys' last use; every REFUSALS_FLUSH_S, the anonymous refusals
    counted; every AUDIT_PRUNE_S, the audit retention and the write limit's expired log."""
    pruned_at = refusals_at = time.monotonic()
    pruned_at -= AUDIT_PRUNE_S  # the first prune soon after start
    while True:
        await asyncio.sleep(KEY_FLUSH_S)
        try:
            await asyncio.to_thread(rt.keys.flush_last_used)
            if time.monotonic() - refusals_at >= REFUSALS_FLUSH_S:
                refusals_at = time.monotonic()
                await asyncio.to_thread(rt.refusals.flush, rt.engine)
            if time.monotonic() - pruned_at >= AUDIT_PRUNE_S:
                pruned_at = time.monotonic()
                n = await asyncio.to_thread(prune_audit, rt.engine, rt.api.audit_retention_days)
                if n:
                    log.info("audit retention: deleted %d entries", n)
                await rt.db(prune_write_hits, rt.api.write_window_s)
        except Exception as exc:  # the database may be away; this waits for next round
            if permanent_fault(exc):
                raise  # its supervisor ends the process
            log.warning("recording key use or audit failed: %s", exc)


def _flush_refusals(rt: Runtime) -> None:
    try:
        rt.refusals.flush(rt.engine)
    except Exception as exc:
        log.warning("anonymous refusals not written at shutdown: %s", exc)
