"""The API's parts of a running gateway's lifespan (see app/main.py): what the routers reach
(`Runtime`), and being ready to serve."""

from __future__ import annotations

import gc
from collections.abc import AsyncIterator, Callable
from contextlib import asynccontextmanager
from typing import TYPE_CHECKING, Any

from eqgw.api.warmup import warm_up
from eqgw.security.audit import AuditLog
from eqgw.security.keys import KeyAuthenticator
from eqgw.security.limits import RateLimiter
from eqgw.store.history_cache import HistoryCache
from eqgw.web.runtime import Runtime

if TYPE_CHECKING:
    from fastapi import FastAPI
    from sqlalchemy import Engine

    from eqgw.api.metrics import Metrics
    from eqgw.commands.service import CommandService
    from eqgw.config import Settings
    from eqgw.fleet.sync import DepotMap
    from eqgw.ingest.service import IngestService
    from eqgw.web.settings import ApiSettings

# The collector's generation thresholds while the gateway serves (see `serving`).
GC_THRESHOLDS = (10_000, 20, 20)

# Whether the process that runs gateways within itself said it manages the collector itself
# (`host_manages_collector`).
_host_manages_collector = False


def host_manages_collector(manages: bool = True) -> bool:
    """Say that this process manages the collector itself (it froze its own heap): the
    gateways it runs from now on leave the collector as it is without looking (`serving`).
    Returns what was said before. Without it a gateway looks at its start, and
    `gc.get_freeze_count()` walks every frozen object: 20 ms of CPU in a process of 300,000
    of them, at each start of a gateway."""
    global _host_manages_collector
    before = _host_manages_collector
    _host_manages_collector = manages
    return before


def collector_managed_by_host() -> bool:
    """What `host_manages_collector` said last (False if nothing)."""
    return _host_manages_collector


def runtime(
    settings: Settings,
    api: ApiSettings,
    engine: Engine,
    ingest: IngestService,
    commands: CommandService,
    depots: DepotMap,
    metrics: Metrics,
    sim: Any = None,
) -> Runtime:
    """Everything the routers reach, attached to the metrics."""
    rt = Runtime(
        settings=settings,
        api=api,
        engine=engine,
        ingest=ingest,
        commands=commands,
        keys=KeyAuthenticator(engine, api.key_cache_s, depots=depots),
        limiter=RateLimiter(api.write_rate, api.write_window_s, engine),
        audit_log=AuditLog(),
        fleet=sim,
        history=HistoryCache(max_buckets=api.history_cache_buckets),
    )
    metrics.attach(rt)
    return rt


@asynccontextmanager
async def serving(app: FastAPI, on_ready: Callable[[], None] | None) -> AsyncIterator[None]:
    """Ready: the API's lazily built parts built (its first request would take them on;
    /readyz cannot answer before this), startup's heap frozen, `on_ready` called.

    What startup built (modules, the app, its route tables, the fleet) lives as long as the
    process: out of the collector's sight, a full collection walks only what came later, a
    few milliseconds instead of 100+ ms with every thread stopped (each such pause was a
    latency spike of every request, frame and websocket). Young collections every 10,000
    allocations instead of 700: requests and frames allocate fast and almost all of it dies
    young, freed by reference counting.

    A process whose heap is frozen already when the gateway starts (an application that runs
    the gateway within itself, a test run), or that said it manages the collector itself
    (`host_manages_collector`), manages it: the gateway then leaves it as it is (unfreezing
    at its end would thaw what that process froze)."""
    app.state.warm_up_s = await warm_up(app)
    owner = not _host_manages_collector and gc.get_freeze_count() == 0
    thresholds = gc.get_threshold()
    if owner:
        gc.collect()
        gc.freeze()
        gc.set_threshold(*GC_THRESHOLDS)
    try:
        if on_ready is not None:
            on_ready()
        yield
    finally:
        if owner:
            gc.set_threshold(*thresholds)
            gc.unfreeze()
