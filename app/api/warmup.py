"""What the API would otherwise build on its first requests, built before the gateway is ready.

FastAPI builds each router's route table on the first request routed through it. `warm_up`
builds them before the lifespan says ready: a request that no route matches walks every
router, sent to the router itself (no metric, no audit entry). The latency metric's route
templates need no warm-up (create_app reads them off the routers,
`eqgw.api.metrics.documented_paths`); the OpenAPI document, every schema of every route
(0.4 s of CPU), is built when `/openapi.json` or `/docs` is first asked for.
"""

from __future__ import annotations

import logging
import time
from collections.abc import MutableMapping
from typing import Any

from fastapi import FastAPI

log = logging.getLogger(__name__)

WARM_UP_PATH = "/__eqgw_warm_up__"


async def warm_up(app: FastAPI) -> float:
    """Build the lazily built parts of the API; returns the seconds it took."""
    start = time.perf_counter()
    await _route_miss(app)
    took = time.perf_counter() - start
    log.info("API warmed up in %.2f s", took)
    return took


async def _route_miss(app: FastAPI) -> None:
    """One GET routed through every router without matching (answered 404)."""
    scope: dict[str, Any] = {
        "type": "http",
        "asgi": {"version": "3.0", "spec_version": "2.3"},
        "http_version": "1.1",
        "method": "GET",
        "scheme": "http",
        "path": WARM_UP_PATH,
        "raw_path": WARM_UP_PATH.encode(),
        "root_path": "",
        "query_string": b"",
        "headers": [(b"host", b"localhost")],
        "client": ("127.0.0.1", 0),
        "server": ("127.0.0.1", 0),
        "state": {},
    }
    sent: list[MutableMapping[str, Any]] = []

    async def receive() -> dict[str, Any]:
        return {"type": "http.request", "body": b"", "more_body": False}

    async def send(message: MutableMapping[str, Any]) -> None:
        sent.append(message)

    await app.router(scope, receive, send)
    status = next((m.get("status") for m in sent if m["type"] == "http.response.start"), None)
    if status != 404:
        log.warning("API warm-up: %s answered %s, not 404", WARM_UP_PATH, status)
