"""docker-compose.yml and the Dockerfile, checked without Docker: the compose file parses and
its services agree with each other and with the fleet file, and the commands the image and the
compose services run are run here, exactly as written (only host names, ports, the database URL
and the buffer path are substituted), against the real PostgreSQL."""

from __future__ import annotations

import json
import re
import shlex
import sys
import tomllib
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

import httpx
import yaml

from eqgw.config import load_settings
from tests.proc_helpers import ROOT, Process, free_port, wait_until
from tests.support import web

COMPOSE = ROOT / "docker-compose.yml"
DOCKERFILE = ROOT / "Dockerfile"
SERVICES = ("postgres", "simulator", "eqgw", "forwarder")
KEY = re.compile(r"\beqgw_[A-Za-z0-9_-]{20,}")


def _compose() -> dict[str, Any]:
    data: dict[str, Any] = yaml.safe_load(COMPOSE.read_text())
    return data


def _dockerfile() -> tuple[list[str], list[str], dict[str, str]]:
    """ENTRYPOINT, CMD (exec form) and ENV of the Dockerfile."""
    text = re.sub(r"\\\n", " ", DOCKERFILE.read_text())
    entry: list[str] = []
    cmd: list[str] = []
    env: dict[str, str] = {}
    for line in text.splitlines():
        word, _, rest = line.strip().partition(" ")
        if word == "ENTRYPOINT":
            entry = json.loads(rest)
        elif word == "CMD":
            cmd = json.loads(rest)
        elif word == "ENV":
            for item in shlex.split(rest):
                k, _, v = item.partition("=")
                env[k] = v
    return entry, cmd, env


def _argv(entry: list[str], command: list[str]) -> list[str]:
    """The container's command line, with the `eqgw` entry point as this checkout's module."""
    assert entry == ["eqgw"]
    return [sys.executable, "-m", "eqgw.cli", *command]


def test_compose_file_parses_and_hangs_together() -> None:
    c = _compose()
    services = c["services"]
    assert tuple(services) == SERVICES
    entry, cmd, env = _dockerfile()
    assert entry == ["eqgw"] and cmd == ["serve"]
    # One image, built from this directory, for every eqgw service.
    for name in ("simulator", "eqgw", "forwarder"):
        assert services[name]["image"] == "eqgw:latest" and services[name]["build"] == "."
    pg = services["postgres"]["environment"]
    gw = services["eqgw"]
    url = urlsplit(gw["environment"]["EQGW_DATABASE_URL"])
    assert url.scheme == "postgresql+psycopg" and url.hostname == "postgres"
    assert (url.username, url.password, url.path.lstrip("/")) == (
        pg["POSTGRES_USER"],
        pg["POSTGRES_PASSWORD"],
        pg["POSTGRES_DB"],
    )
    assert gw["depends_on"]["postgres"]["condition"] == "service_healthy"
    # The published port is the one the image listens on.
    assert gw["ports"] == [f"{env['EQGW_API_PORT']}:{env['EQGW_API_PORT']}"]
    assert env["EQGW_API_HOST"] == "0.0.0.0"
    # The fleet file is mounted where EQGW_CONFIG points, and it loads.
    source, target = gw["volumes"][0].split(":")[:2]
    assert target == gw["environment"]["EQGW_CONFIG"]
    settings = load_settings(ROOT / source)
    # Its buses are the simulator's, at the simulator's address.
    sim = services["simulator"]["command"]
    assert sim[0] == "simulate"
    n = int(sim[sim.index("--vehicles") + 1])
    port = int(sim[sim.index("--listen") + 1].rpartition(":")[2])
    names = [f"SIM-{i:03d}" for i in range(1, n + 1)]
    for bus in settings.buses:
        assert bus.interface == "socketcand" and bus.channel in names
        assert bus.options == {"host": "simulator", "port": port}
    # The forwarder reads a vehicle the gateway does not, and sends it to the gateway.
    fwd = services["forwarder"]["command"]
    assert fwd[0] == "forward"
    vehicle = fwd[fwd.index("--vehicle") + 1]
    assert vehicle in {v.id for v in settings.vehicles}
    assert vehicle not in {b.vehicle_id for b in settings.buses}
    assert fwd[fwd.index("--bus") + 1] == f"socketcand:{vehicle}"
    assert "host=simulator" in fwd and f"port={port}" in fwd
    assert fwd[fwd.index("--to") + 1] == f"http://eqgw:{env['EQGW_API_PORT']}/api/v1"
    assert services["forwarder"]["environment"] == {"EQGW_FORWARD_KEY": "${EQGW_FORWARD_KEY:-}"}


def _substitute(args: list[str], table: dict[str, str]) -> list[str]:
    out = []
    for a in args:
        for old, new in table.items():
            a = a.replace(old, new)
        out.append(a)
    return out


def test_the_images_commands_run_here(pg_url: str, tmp_path: Path) -> None:
    """simulator, eqgw (the image's ENTRYPOINT + CMD) and the forwarder, as compose runs them."""
    services = _compose()["services"]
    entry, cmd, image_env = _dockerfile()
    sim_cmd = services["simulator"]["command"]
    listen = sim_cmd[sim_cmd.index("--listen") + 1]
    sim = Process(_argv(entry, _substitute(sim_cmd, {listen: "127.0.0.1:0"})), tmp_path)
    procs = [sim]
    try:
        m = wait_until(lambda: re.search(r"listening 127.0.0.1:(\d+)", sim.output()), 60, "sim")
        sim_port = m.group(1)
        # The simulator's own description agrees with the fleet file's equalizer addresses.
        gw = services["eqgw"]
        fleet = ROOT / gw["volumes"][0].split(":")[0]
        settings = load_settings(fleet)
        for bus in settings.buses:
            line = wait_until(
                lambda b=bus: re.search(rf"{b.channel}\s+\d+-series\s+SA (\S+)", sim.output()),
                30,
                "the simulator's bus list",
            )
            assert [int(x) for x in line.group(1).split(",")] == bus.equalizer_sas
        text = fleet.read_text().replace("simulator", "127.0.0.1")
        text = text.replace(f"port = {listen.rpartition(':')[2]}", f"port = {sim_port}")
        config = tmp_path / "fleet.toml"
        config.write_text(text)
        tomllib.loads(text)
        api_port = free_port()
        env = {
            **image_env,
            **gw["environment"],
            "EQGW_DATABASE_URL": pg_url,
            "EQGW_CONFIG": str(config),
            "EQGW_API_PORT": str(api_port),
        }
        eqgw = Process(_argv(entry, cmd), tmp_path, env)
        procs.append(eqgw)
        base = f"http://127.0.0.1:{api_port}"

        def healthy() -> bool:
            assert eqgw.proc.poll() is None, eqgw.output()
            try:
                return web.get(f"{base}/healthz", timeout=2).status_code == 200
            except httpx.TransportError:
                return False

        wait_until(healthy, 90, "eqgw serve")
        admin = wait_until(lambda: KEY.search(eqgw.output()), 30, "the first admin key").group(0)
        auth = {"Authorization": f"Bearer {admin}"}

        def online() -> set[str]:
            r = web.get(f"{base}/api/v1/vehicles", headers=auth, timeout=10)
            return {v["id"] for v in r.json()["vehicles"] if v["online"]}

        wanted = {b.vehicle_id for b in settings.buses}
        wait_until(lambda: online() >= wanted, 60, "the compose fleet online")
        # The way docs/deploy.md gives to a forwarder key, then the compose forwarder's command.
        keys = Process(
            _argv(
                entry,
                ["keys", "create", "--role", "ingest", "--name", "SIM-005", "--vehicle", "SIM-005"],
            ),
            tmp_path,
            env,
        )
        assert keys.proc.wait(timeout=60) == 0, keys.output()
        keys.stop()
        ingest_key = KEY.search(keys.output())
        assert ingest_key, keys.output()
        fwd_cmd = _substitute(
            services["forwarder"]["command"],
            {
                "host=simulator": "host=127.0.0.1",
                f"port={listen.rpartition(':')[2]}": f"port={sim_port}",
                "http://eqgw:8000": base,
                "/var/lib/eqgw/forward.db": str(tmp_path / "forward.db"),
            },
        )
        fwd = Process(_argv(entry, fwd_cmd), tmp_path, {"EQGW_FORWARD_KEY": ingest_key.group(0)})
        procs.append(fwd)
        vehicle = fwd_cmd[fwd_cmd.index("--vehicle") + 1]

        def forwarded() -> bool:
            r = web.get(f"{base}/api/v1/vehicles/{vehicle}/history", headers=auth, timeout=10)
            return r.status_code == 200 and bool(r.json()["series"].get("v12"))

        wait_until(forwarded, 60, "the forwarded vehicle's history")
    finally:
        for p in reversed(procs):
            p.stop()
