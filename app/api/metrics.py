"""Prometheus metrics: ingest, buses, writer, commands, the alert engine (read at scrape time)
and API latency."""

from __future__ import annotations

import asyncio
import platform
import re
import time
from collections.abc import Iterable, Iterator, Mapping, Sequence
from typing import TYPE_CHECKING, Any

from fastapi import APIRouter
from fastapi.routing import APIRoute
from prometheus_client import (
    CollectorRegistry,
    Counter,
    Gauge,
    Histogram,
    Info,
    ProcessCollector,
    generate_latest,
)
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, Metric
from prometheus_client.registry import Collector
from starlette.types import ASGIApp, Receive, Scope, Send

if TYPE_CHECKING:
    from eqgw.alerts.engine import AlertEngine
    from eqgw.web.runtime import Runtime

BUS_STATES = ("connecting", "open", "backoff", "closed")
TASK_STATES = ("running", "backoff", "done", "failed")
# How often the event-loop lag probe wakes up.
LOOP_PROBE_S = 0.1
SEVERITIES = ("info", "warning", "critical")


class GatewayCollector(Collector):
    """Reads the running gateway's counters when Prometheus scrapes."""

    def __init__(self, rt: Runtime) -> None:
        self.rt = rt

    def collect(self) -> Iterator[Metric]:
        st = self.rt.ingest.status()
        p = st["pipeline"]
        yield CounterMetricFamily("eqgw_frames", "Frames given to the decoder", value=p["frames"])
        yield CounterMetricFamily("eqgw_records", "Records decoded", value=p["records"])
        yield CounterMetricFamily(
            "eqgw_other_nodes_dm1_transfers",
            "DM1s other nodes (not the equalizers) sent one another by RTS/CTS (not decoded)",
            value=p.get("other_dm1_transfers", 0),
        )
        # The writer's, buses' and tasks' figures are JSON objects, read here by key.
        w: Mapping[str, Any] = st["writer"]
        yield CounterMetricFamily(
            "eqgw_rows_committed", "Rows committed to the database", value=w["committed_rows"]
        )
        yield CounterMetricFamily(
            "eqgw_rows_refused", "Rows refused while the writer was full", value=w["refused_rows"]
        )
        yield GaugeMetricFamily(
            "eqgw_writer_pending_rows",
            "Rows waiting for the database",
            value=w["pending_rows"],
        )
        yield GaugeMetricFamily(
            "eqgw_writer_lag_seconds",
            "How long the oldest row waiting for the database has waited (0: none waits)",
            value=w["lag_s"],
        )
        yield CounterMetricFamily(
            "eqgw_writer_failures", "Failed database batches", value=w["failures"]
        )
        yield GaugeMetricFamily(
            "eqgw_writer_journal_rows",
            "Rows kept in the local journal until the database has them",
            value=w["journal_rows"],
        )
        yield CounterMetricFamily(
            "eqgw_writer_rejected_rows",
            "Rows the writer could not build into a batch (logged, dropped)",
            value=w["rejected_rows"],
        )
        yield CounterMetricFamily(
            "eqgw_writer_errors",
            "Unexpected errors of the writer thread (each logged; it started again)",
            value=w["crashes"],
        )
        frames = CounterMetricFamily("eqgw_bus_frames", "Frames received per bus", labels=["bus"])
        drops = CounterMetricFamily("eqgw_bus_drops", "Frames dropped per bus", labels=["bus"])
        state = GaugeMetricFamily(
            "eqgw_bus_state", "1 for the bus's state", labels=["bus", "state"]
        )
        stalled = GaugeMetricFamily(
            "eqgw_bus_stalled",
            "1 while a socketcand link took frames and received none for its stall_after_s "
            "(frames are held back until it drains)",
            labels=["bus"],
        )
        handed = CounterMetricFamily(
            "eqgw_bus_frames_handed", "Frames handed to the interface per bus", labels=["bus"]
        )
        answers = CounterMetricFamily(
            "eqgw_bus_j1939_answers",
            "The gateway's answers to other nodes per bus (J1939-21): nacks, sessions_accepted, "
            "sessions_completed, sessions_aborted; withheld: decided while it could not "
            "transmit (no address, fenced), not sent",
            labels=["bus", "kind"],
        )
        buses: Sequence[Mapping[str, Any]] = st["buses"]
        for b in buses:
            for kind, n in (b.get("answers") or {}).items():
                answers.add_metric([b["name"], kind], n)
            stalled.add_metric([b["name"]], 1.0 if b.get("stalled") else 0.0)
            handed.add_metric([b["name"]], b.get("frames_handed", 0))
            frames.add_metric([b["name"]], b["frames_total"])
            drops.add_metric([b["name"]], b["drops"])
            for s in BUS_STATES:
                state.add_metric([b["name"], s], 1.0 if b["state"] == s else 0.0)
        yield frames
        yield drops
        yield state
        yield stalled
        yield handed
        yield answers
        restarts = CounterMetricFamily(
            "eqgw_task_restarts",
            "Background tasks started again after a failure",
            labels=["task"],
        )
        task_state = GaugeMetricFamily(
            "eqgw_task_state", "1 for a background task's state", labels=["task", "state"]
        )
        tasks: Sequence[Mapping[str, Any]] = st.get("tasks", [])
        for t in tasks:
            restarts.add_metric([t["name"]], t["restarts"])
            for s in TASK_STATES:
                task_state.add_metric([t["name"], s], 1.0 if t["state"] == s else 0.0)
        yield restarts
        yield task_state
        hub = st["hub"]
        yield GaugeMetricFamily(
            "eqgw_hub_subscribers",
            "Subscribers of the ingest's event hub (websockets, the alert engine, the cluster)",
            value=hub["subscribers"],
        )
        yield CounterMetricFamily(
            "eqgw_hub_dropped_subscribers",
            "Subscribers dropped for falling behind",
            value=hub["dropped_subscribers"],
        )
        outcomes = CounterMetricFamily(
            "eqgw_command_outcomes",
            "Commands ended, by kind and final state",
            labels=["kind", "state"],
        )
        for (kind, state_), n in sorted(self.rt.commands.outcomes.items()):
            outcomes.add_metric([kind, state_], n)
        yield outcomes
        yield CounterMetricFamily(
            "eqgw_command_frames_sent",
            "Frames sent for commands",
            value=self.rt.commands.frames_sent,
        )
        cache = self.rt.history
        reads = CounterMetricFamily(
            "eqgw_history_cache_reads",
            "History reads of rollups by cache outcome: hit (checked and served), miss (no "
            "span held), stale (a span found changed or too old and read again)",
            labels=["outcome"],
        )
        reads.add_metric(["hit"], cache.stats.hits)
        reads.add_metric(["miss"], cache.stats.misses)
        reads.add_metric(["stale"], cache.stats.stale)
        yield reads
        yield GaugeMetricFamily(
            "eqgw_history_cache_buckets",
            "Rollup buckets held by the history cache",
            value=cache.size,
        )


class AlertEngineCollector(Collector):
    """The alert engine's counters (this gateway's engine: the units it evaluates)."""

    def __init__(self, engine: AlertEngine | None) -> None:
        self.engine = engine

    def collect(self) -> Iterator[Metric]:
        e = self.engine
        yield GaugeMetricFamily(
            "eqgw_alert_engine_running",
            "1 while the alert engine's loops run (0: disabled or stopped)",
            value=1.0 if e is not None and e.running else 0.0,
        )
        if e is None:
            return
        st = e.status()
        raised = CounterMetricFamily(
            "eqgw_alerts_raised", "Alerts raised, by rule and severity", labels=["rule", "severity"]
        )
        for (rule, sev), n in sorted(e.raised_by.items()):
            raised.add_metric([rule, sev], n)
        yield raised
        cleared = CounterMetricFamily(
            "eqgw_alerts_cleared",
            "Alerts cleared (condition gone, rule disabled or deleted), by rule and severity",
            labels=["rule", "severity"],
        )
        for (rule, sev), n in sorted(e.cleared_by.items()):
            cleared.add_metric([rule, sev], n)
        yield cleared
        open_ = GaugeMetricFamily(
            "eqgw_alerts_open",
            "Open alerts (active or acknowledged), by severity",
            labels=["severity"],
        )
        by_sev = e.open_by_severity()
        for sev in sorted({*SEVERITIES, *by_sev}):
            open_.add_metric([sev], by_sev[sev])
        yield open_
        yield CounterMetricFamily(
            "eqgw_alert_evaluations",
            "Rule evaluations (one rule on one unit)",
            value=st["evaluations"],
        )
        yield CounterMetricFamily(
            "eqgw_alert_engine_resyncs",
            "Times the engine fell a whole hub queue behind and re-evaluated every unit",
            value=st["resyncs"],
        )
        yield CounterMetricFamily(
            "eqgw_alert_engine_db_failures",
            "Raises or clears that failed on the database (retried at the next evaluation)",
            value=st["db_failures"],
        )
        yield GaugeMetricFamily(
            "eqgw_alert_engine_backlog_events",
            "Events queued for the engine, not yet evaluated (its lag)",
            value=st["backlog"],
        )
        yield GaugeMetricFamily("eqgw_alert_rules", "Alert rules loaded", value=st["rules"])


class Metrics:
    """A registry per app (tests run several apps in one process)."""

    def __init__(self) -> None:
        from eqgw import version

        self.registry = CollectorRegistry()
        # process_cpu_seconds_total, process_resident_memory_bytes, open fds, start time.
        ProcessCollector(registry=self.registry)
        Info("eqgw_build", "The running eqgw", registry=self.registry).info(
            {"version": version(), "python": platform.python_version()}
        )
        self.websockets = Gauge(
            "eqgw_ws_subscribers",
            "Websocket clients connected (dashboards, API clients)",
            registry=self.registry,
        )
        self.ws_refused = Counter(
            "eqgw_ws_refused",
            "Websockets refused for a bound on open ones: limit=key (EQGW_API_WS_MAX_PER_KEY) "
            "or client (EQGW_API_WS_MAX_PER_CLIENT, per client address)",
            ["limit"],
            registry=self.registry,
        )
        for limit in ("key", "client"):
            self.ws_refused.labels(limit)  # both series from the start, at 0
        self.latency = Histogram(
            "eqgw_api_request_seconds",
            "API latency by route",
            ["method", "route", "status"],
            registry=self.registry,
            buckets=(0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1, 2.5),
        )
        self.loop_lag = Histogram(
            "eqgw_event_loop_lag_seconds",
            "How late the event loop ran a timer that was due (every request, websocket and "
            "frame waits behind the code the loop runs)",
            registry=self.registry,
            buckets=(0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1, 2.5),
        )
        # Route templates of the latency metric's labels (loaded by the warm-up, or the first
        # request without one).
        self.routes = RouteTemplates()

    async def watch_loop(self, interval_s: float = LOOP_PROBE_S) -> None:
        """Sleep `interval_s` again and again, recording how late each wake-up came."""
        loop = asyncio.get_running_loop()
        while True:
            due = loop.time() + interval_s
            await asyncio.sleep(interval_s)
            self.loop_lag.observe(max(0.0, loop.time() - due))

    def attach(self, rt: Runtime) -> None:
        self.registry.register(GatewayCollector(rt))

    def exposition(self, alerts: AlertEngine | None) -> bytes:
        """The text exposition: the registry, then the alert engine's figures.

        The engine comes from the app at scrape time (`app.state.alerts`, set by the lifespan
        and None when alerting is disabled), so it is not tied to the registry's life.
        """
        return generate_latest(self.registry) + generate_latest(AlertEngineCollector(alerts))


# Routes outside the OpenAPI document, by template; `/static/...` is one label.
_EXTRA_ROUTES = ("/", "/docs", "/openapi.json", "/api/v1/ws")
_STATIC = "/static"


def documented_paths(routers: Iterable[tuple[APIRouter, str]]) -> list[str]:
    """The paths of the OpenAPI document of an app that includes `routers` (router, prefix)
    in that order, as FastAPI lists them (each `APIRoute` in the schema, by its prefixed
    `path_format`, first occurrence), without building the document's schemas (0.4 s of CPU;
    tests/test_metrics_exposition.py holds the two equal)."""
    seen: dict[str, None] = {}
    for router, prefix in routers:
        for route in router.routes:
            if isinstance(route, APIRoute) and route.include_in_schema:
                seen.setdefault(prefix + route.path_format, None)
    return list(seen)


class RouteTemplates:
    """The route template of a request path (`/api/v1/vehicles/{vehicle_id}/live`), from the
    app's documented paths: full paths with their prefix, and the same whichever way FastAPI
    resolved the route (the documents and the static files have no route in the scope)."""

    def __init__(self) -> None:
        self._exact: dict[str, str] = {}
        self._patterns: list[tuple[re.Pattern[str], str]] = []
        # The documented paths loaded (create_app, from its routers); none: every request
        # outside the extra routes is `unmatched`.
        self.documented: list[str] = []

    def load(self, documented: list[str]) -> None:
        """Take the app's documented paths (`documented_paths`) and the extra routes."""
        self.documented = documented
        for template in documented + list(_EXTRA_ROUTES):
            if "{" in template:
                regex = re.sub(r"\\{[^/]+?\\}", "[^/]+", re.escape(template))
                self._patterns.append((re.compile(regex + "$"), template))
            else:
                self._exact[template] = template

    def label(self, scope: Scope) -> str:
        path: str = scope["path"]
        found = self._exact.get(path)
        if found is not None:
            return found
        if path.startswith(_STATIC + "/"):
            return _STATIC
        for pattern, template in self._patterns:
            if pattern.match(path):
                return template
        return "unmatched"


class LatencyMiddleware:
    """Times every HTTP request by route template (pure ASGI: cheap on the hot path)."""

    def __init__(self, app: ASGIApp, metrics: Metrics) -> None:
        self.app = app
        self.metrics = metrics
        self.routes = metrics.routes

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        start = time.perf_counter()
        status: dict[str, Any] = {"code": 500}

        async def send_wrapper(message: Any) -> None:
            if message["type"] == "http.response.start":
                status["code"] = message["status"]
            await send(message)

        try:
            await self.app(scope, receive, send_wrapper)
        finally:
            path = self.routes.label(scope)
            self.metrics.latency.labels(scope["method"], path, str(status["code"])).observe(
                time.perf_counter() - start
            )
