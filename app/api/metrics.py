"""Prometheus metrics: ingest, buses, writer, commands (read at scrape time) and API latency."""

from __future__ import annotations

import time
from collections.abc import Iterator
from typing import TYPE_CHECKING, Any

from prometheus_client import CollectorRegistry, Histogram
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, Metric
from prometheus_client.registry import Collector
from starlette.types import ASGIApp, Receive, Scope, Send

if TYPE_CHECKING:
    from app.api.deps import Runtime

BUS_STATES = ("connecting", "open", "backoff", "closed")


class GatewayCollector(Collector):
    """Reads the running gateway's counters when Prometheus scrapes."""

    def __init__(self, rt: Runtime) -> None:
        self.rt = rt

    def collect(self) -> Iterator[Metric]:
        st = self.rt.ingest.status()
        p = st["pipeline"]
        yield CounterMetricFamily("eqgw_frames", "Frames given to the decoder", value=p["frames"])
        yield CounterMetricFamily("eqgw_records", "Records decoded", value=p["records"])
        w = st["writer"]
        yield CounterMetricFamily(
            "eqgw_rows_committed", "Rows committed to the database", value=w["committed_rows"]
        )
        yield CounterMetricFamily(
            "eqgw_rows_refused", "Rows refused while the writer was full", value=w["refused_rows"]
        )
        yield GaugeMetricFamily(
            "eqgw_writer_pending_rows", "Rows waiting for the database (writer lag)",
            value=w["pending_rows"],
        )  # fmt: skip
        yield CounterMetricFamily(
            "eqgw_writer_failures", "Failed database batches", value=w["failures"]
        )
        frames = CounterMetricFamily("eqgw_bus_frames", "Frames received per bus", labels=["bus"])
        drops = CounterMetricFamily("eqgw_bus_drops", "Frames dropped per bus", labels=["bus"])
        state = GaugeMetricFamily(
            "eqgw_bus_state", "1 for the bus's state", labels=["bus", "state"]
        )
        for b in st["buses"]:
            frames.add_metric([b["name"]], b["frames_total"])
            drops.add_metric([b["name"]], b["drops"])
            for s in BUS_STATES:
                state.add_metric([b["name"], s], 1.0 if b["state"] == s else 0.0)
        yield frames
        yield drops
        yield state
        hub = st["hub"]
        yield GaugeMetricFamily(
            "eqgw_ws_subscribers", "Event subscribers", value=hub["subscribers"]
        )
        yield CounterMetricFamily(
            "eqgw_hub_dropped_subscribers", "Subscribers dropped for falling behind",
            value=hub["dropped_subscribers"],
        )  # fmt: skip
        outcomes = CounterMetricFamily(
            "eqgw_command_outcomes", "Commands ended, by kind and final state",
            labels=["kind", "state"],
        )  # fmt: skip
        for (kind, state_), n in sorted(self.rt.commands.outcomes.items()):
            outcomes.add_metric([kind, state_], n)
        yield outcomes
        yield CounterMetricFamily(
            "eqgw_command_frames_sent", "Frames sent for commands",
            value=self.rt.commands.frames_sent,
        )  # fmt: skip


class Metrics:
    """A registry per app (tests run several apps in one process)."""

    def __init__(self) -> None:
        self.registry = CollectorRegistry()
        self.latency = Histogram(
            "eqgw_api_request_seconds",
            "API latency by route",
            ["method", "route", "status"],
            registry=self.registry,
            buckets=(0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1, 2.5),
        )

    def attach(self, rt: Runtime) -> None:
        self.registry.register(GatewayCollector(rt))


class LatencyMiddleware:
    """Times every HTTP request by route template (pure ASGI: cheap on the hot path)."""

    def __init__(self, app: ASGIApp, metrics: Metrics) -> None:
        self.app = app
        self.metrics = metrics

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
            route = scope.get("route")
            path = getattr(route, "path", "unmatched")
            self.metrics.latency.labels(scope["method"], path, str(status["code"])).observe(
                time.perf_counter() - start
            )
