"""/metrics of a running `eqgw serve`: process and build figures, websockets counted as
websockets, and every request labelled by its route template (documents included)."""

from __future__ import annotations

import asyncio
import re
from pathlib import Path

import pytest
import websockets
from prometheus_client.parser import text_string_to_metric_families

from eqgw import version
from tests.proc_helpers import Process, eqgw, free_port, wait_until
from tests.support import web

KEY = re.compile(r"\beqgw_[A-Za-z0-9_-]{20,}")


def _samples(text: str) -> dict[tuple[str, tuple[tuple[str, str], ...]], float]:
    """Every sample of the exposition (the parser refuses malformed text)."""
    return {
        (s.name, tuple(sorted(s.labels.items()))): s.value
        for family in text_string_to_metric_families(text)
        for s in family.samples
    }


@pytest.mark.parametrize("docs", [True, False])
def test_the_metrics_route_templates_are_the_documents_paths(tmp_path: Path, docs: bool) -> None:
    """The latency metric's templates, read off the routers without building the OpenAPI
    document, are the document's paths in its order (a route FastAPI documents differently
    would be labelled `unmatched`)."""
    from eqgw.config import Settings
    from eqgw.main import create_app
    from eqgw.web.settings import ApiSettings

    app = create_app(
        Settings(database_url=f"sqlite:///{tmp_path / 'eqgw.db'}"), api=ApiSettings(docs=docs)
    )
    documented = app.state.metrics.routes.documented
    assert len(documented) > 30
    assert documented == list(app.openapi()["paths"])


def test_metrics_of_a_running_gateway(tmp_path: Path) -> None:
    port = free_port()
    env = {"EQGW_DATABASE_URL": f"sqlite:///{tmp_path / 'eqgw.db'}"}
    proc = Process(eqgw("serve", "--port", str(port), "--simulate", "1"), tmp_path, env)
    base = f"http://127.0.0.1:{port}"
    try:
        key = proc.wait_line(KEY).group(0)
        proc.wait_line(re.compile("serving on"))
        for path in (
            "/docs",
            "/openapi.json",
            "/static/js/api.js",
            "/api/v1/vehicles/SIM-001/live",
        ):
            r = web.get(base + path, headers={"Authorization": f"Bearer {key}"}, timeout=10)
            assert r.status_code == 200, (path, r.status_code)

        def scrape() -> dict[tuple[str, tuple[tuple[str, str], ...]], float]:
            return _samples(web.get(f"{base}/metrics", timeout=10).text)

        def gauge(name: str) -> float:
            return scrape()[(name, ())]

        before_hub = gauge("eqgw_hub_subscribers")
        assert gauge("eqgw_ws_subscribers") == 0

        async def two_sockets() -> None:
            url = f"ws://127.0.0.1:{port}/api/v1/ws?key={key}"
            async with websockets.connect(url) as one, websockets.connect(url) as two:
                async with asyncio.timeout(30):  # a silent socket fails, never hangs
                    await one.recv()  # the snapshot: the socket is subscribed
                    await two.recv()
                counted = await asyncio.to_thread(gauge, "eqgw_ws_subscribers")
                assert counted == 2
                hub = await asyncio.to_thread(gauge, "eqgw_hub_subscribers")
                assert hub == before_hub + 2  # each socket is one hub subscriber
            await asyncio.to_thread(
                wait_until, lambda: gauge("eqgw_ws_subscribers") == 0, 30, "sockets closed"
            )

        asyncio.run(two_sockets())

        samples = scrape()
        names = {name for name, _ in samples}
        assert {
            "process_cpu_seconds_total",
            "process_resident_memory_bytes",
            "process_start_time_seconds",
            "process_open_fds",
        } <= names, sorted(names)
        build = [labels for name, labels in samples if name == "eqgw_build_info"]
        assert len(build) == 1 and ("version", version()) in build[0], build
        routes = {
            dict(labels)["route"]
            for name, labels in samples
            if name == "eqgw_api_request_seconds_count"
        }
        assert {
            "/docs",
            "/openapi.json",
            "/static",
            "/api/v1/vehicles/{vehicle_id}/live",
        } <= routes, routes
        assert not any("SIM-001" in r for r in routes), routes
    finally:
        proc.stop()
