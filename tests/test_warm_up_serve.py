"""`eqgw serve` says ready only once the API's lazily built parts are built (the route
templates the latency metric labels requests by, FastAPI's route tables): before, the first
request after ready took 1-2 s. Real process; no timing asserted (bench/first_request.py
prints the first request's latency)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from tests.cluster_helpers import readyz, start_gateway
from tests.proc_helpers import wait_until


def test_ready_only_after_the_warm_up(tmp_path: Path) -> None:
    fleet = tmp_path / "fleet.toml"
    fleet.write_text("")
    gw, base = start_gateway(tmp_path, f"sqlite:///{tmp_path / 'eqgw.db'}", fleet, "warm")
    try:
        answers: list[dict[str, Any]] = []

        def ready() -> bool:
            body = readyz(base)  # None until the gateway listens
            if body is not None:
                answers.append(body)
            return bool(body and body["ready"])

        wait_until(ready, 120, "the gateway ready", interval=0.02)
        # Every answer, the first included, says the warm-up is done: it came before serving.
        assert all(a["warm_up"]["done"] for a in answers), answers
        assert all(a["warm_up"]["seconds"] >= 0 for a in answers), answers
    finally:
        gw.stop()
