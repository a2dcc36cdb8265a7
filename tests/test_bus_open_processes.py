"""Many buses on one socketcand server open a few at a time (`bus_open_concurrency`), not all
at once: a proxy in front of an `eqgw simulate` server counts the connections still opening
while a real `eqgw serve` opens 24 buses through it (`python -m bench.bus_open`: 500)."""

from __future__ import annotations

from pathlib import Path

from tests.cluster_helpers import LISTENING, readyz, start_gateway
from tests.proc_helpers import Process, eqgw, wait_until
from tests.socketcand_proxy import OpeningCounter

BUSES = 24
LIMIT = 4


def fleet_file(path: Path, buses: int, port: int) -> Path:
    """`buses` vehicles, each with its socketcand bus SIM-001... on 127.0.0.1:`port`."""
    lines = []
    for n in range(1, buses + 1):
        lines.append(
            f'[[vehicles]]\nid = "V{n:03d}"\n\n[[buses]]\nname = "V{n:03d}/can0"\n'
            f'vehicle_id = "V{n:03d}"\ninterface = "socketcand"\nchannel = "SIM-{n:03d}"\n'
            f'options = {{ host = "127.0.0.1", port = {port} }}\n'
        )
    path.write_text("\n".join(lines))
    return path


def buses_open(base: str) -> int:
    body = readyz(base) or {}
    return sum(b["state"] == "open" for b in body.get("buses") or [])


def test_buses_open_a_few_at_a_time(tmp_path: Path) -> None:
    sim = Process(
        eqgw("simulate", "--vehicles", str(BUSES), "--listen", "127.0.0.1:0", "--seed", "3"),
        tmp_path,
    )
    proxy: OpeningCounter | None = None
    gw: Process | None = None
    try:
        sim_port = int(sim.wait_line(LISTENING).group(2))
        proxy = OpeningCounter(("127.0.0.1", sim_port)).start()
        fleet = fleet_file(tmp_path / "fleet.toml", BUSES, proxy.port)
        env = {"EQGW_BUS_OPEN_CONCURRENCY": str(LIMIT)}
        db = f"sqlite:///{tmp_path / 'eqgw.db'}"
        gw, base = start_gateway(tmp_path, db, fleet, "opens", extra_env=env)
        wait_until(lambda: buses_open(base) == BUSES, 120, f"all {BUSES} buses open")
        assert proxy.opened >= BUSES
        assert proxy.max_opening <= LIMIT, proxy.max_opening
    finally:
        for proc in (gw, sim):
            if proc is not None and proc.proc.poll() is None:
                proc.stop()
        if proxy is not None:
            proxy.stop()
