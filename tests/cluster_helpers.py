"""Real `eqgw simulate` and `eqgw serve` subprocesses for the several-gateways tests."""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import httpx

from eqgw.security.keys import create_key
from eqgw.store.engine import create_engine
from eqgw.store.migrate import upgrade_engine
from tests.proc_helpers import Process, eqgw, free_port
from tests.support import web

METRICS_TOKEN = "cluster-test-metrics"
LISTENING = re.compile(r"listening (\S+):(\d+)")


def operator_key(db_url: str, name: str) -> str:
    """Migrate the database and create an operator key on it (before any gateway starts)."""
    engine = create_engine(db_url)
    try:
        upgrade_engine(engine)
        _, key = create_key(engine, name, "operator")
    finally:
        engine.dispose()
    return key


def admin_key(db_url: str, name: str = "test admin") -> str:
    """Migrate the database and create a whole-fleet admin key on it."""
    engine = create_engine(db_url)
    try:
        upgrade_engine(engine)
        _, key = create_key(engine, name, "admin")
    finally:
        engine.dispose()
    return key


def start_simulator(tmp_path: Path, vehicles: int, *extra: str) -> tuple[Process, int]:
    sim = Process(
        eqgw("simulate", "--vehicles", str(vehicles), "--listen", "127.0.0.1:0", *extra), tmp_path
    )
    m = sim.wait_line(LISTENING)
    return sim, int(m.group(2))


def write_fleet(path: Path, names: list[str], port: int) -> Path:
    """A fleet file listing the simulator's buses over socketcand."""
    lines = []
    for name in names:
        lines += ["[[vehicles]]", f'id = "{name}"', 'depot = "sim"', ""]
    for name in names:
        lines += [
            "[[buses]]",
            f'name = "{name}"',
            f'vehicle_id = "{name}"',
            'interface = "socketcand"',
            f'channel = "{name}"',
            f'options = {{ host = "127.0.0.1", port = {port} }}',
            "",
        ]
    path.write_text("\n".join(lines))
    return path


def start_gateway(
    tmp_path: Path,
    db_url: str,
    fleet: Path,
    instance: str,
    *,
    lease_period_s: float = 0.5,
    extra_env: dict[str, str] | None = None,
) -> tuple[Process, str]:
    port = free_port()
    env = {
        "EQGW_DATABASE_URL": db_url,
        "EQGW_API_PORT": str(port),
        "EQGW_CLUSTER_INSTANCE_ID": instance,
        "EQGW_CLUSTER_LEASE_PERIOD_S": str(lease_period_s),
        "EQGW_CLUSTER_LEASE_TIMEOUT_S": "2",
        "EQGW_API_METRICS_TOKEN": METRICS_TOKEN,
        **(extra_env or {}),
    }
    proc = Process(eqgw("serve", "--config", str(fleet)), tmp_path, env)
    return proc, f"http://127.0.0.1:{port}"


def readyz(base: str) -> dict[str, Any] | None:
    try:
        r = web.get(
            f"{base}/readyz", headers={"Authorization": f"Bearer {METRICS_TOKEN}"}, timeout=5
        )
    except httpx.HTTPError:
        return None
    body: dict[str, Any] = r.json()
    return body
