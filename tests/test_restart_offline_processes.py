"""`eqgw serve` restarted while one of its buses cannot be reached does not page that bus's
unit as offline: nothing can be heard from a bus that is not open, so the silence is the bus's,
not the unit's. Real processes: two `eqgw simulate` (one per bus) and the gateway, stopped and
started again over one SQLite file."""

from __future__ import annotations

import re
import signal
import time
from pathlib import Path
from typing import Any

from tests.cluster_helpers import LISTENING
from tests.proc_helpers import Process, eqgw, free_port, wait_until
from tests.support import web

SERVING = re.compile(r"serving on")
ADMIN_KEY = re.compile(r"^\s+(eqgw_\S+)\s*$", re.M)
# Long enough that a unit's first frames after a start, on a loaded machine, come within it.
OFFLINE_AFTER_S = 5.0
# A clean stop: uvicorn ends by raising the SIGTERM it handled again, after the shutdown ran.
CLEAN_EXIT = (0, -signal.SIGTERM)


def _simulator(tmp_path: Path, port: int = 0) -> tuple[Process, int]:
    sim = Process(
        eqgw("simulate", "--vehicles", "1", "--listen", f"127.0.0.1:{port}", "--seed", "3"),
        tmp_path,
    )
    return sim, int(sim.wait_line(LISTENING).group(2))


def _fleet(path: Path, ports: dict[str, int]) -> Path:
    lines = [f"[monitor]\noffline_after_s = {OFFLINE_AFTER_S}\n"]
    for vehicle in ports:
        lines.append(f'[[vehicles]]\nid = "{vehicle}"\n')
    for vehicle, port in ports.items():
        lines.append(
            f'[[buses]]\nname = "{vehicle}/can0"\nvehicle_id = "{vehicle}"\n'
            'interface = "socketcand"\nchannel = "SIM-001"\n'
            f'options = {{ host = "127.0.0.1", port = {port} }}\n'
        )
    path.write_text("\n".join(lines))
    return path


def _gateway(tmp_path: Path, db: Path, fleet: Path) -> tuple[Process, str]:
    port = free_port()
    env = {"EQGW_DATABASE_URL": f"sqlite:///{db}", "EQGW_API_PORT": str(port)}
    gw = Process(eqgw("serve", "--config", str(fleet)), tmp_path, env)
    gw.wait_line(SERVING, timeout=120)
    return gw, f"http://127.0.0.1:{port}"


def _get(base: str, key: str, path: str) -> Any:
    r = web.get(f"{base}/api/v1{path}", headers={"Authorization": f"Bearer {key}"}, timeout=10)
    assert r.status_code == 200, r.text
    return r.json()


def _online(base: str, key: str) -> dict[str, bool]:
    return {
        v["id"]: all(u["online"] for u in v["units"]) and bool(v["units"])
        for v in _get(base, key, "/vehicles")["vehicles"]
    }


def _last_seen(base: str, key: str, vehicle: str) -> float:
    """The latest frame of the vehicle's units (epoch seconds; -inf: none heard)."""
    for v in _get(base, key, "/vehicles")["vehicles"]:
        if v["id"] == vehicle:
            heard = [u["last_seen"] for u in v["units"] if u["last_seen"] is not None]
            return max(heard, default=float("-inf"))
    raise AssertionError(f"no vehicle {vehicle}")


def _offline_episodes(base: str, key: str, vehicle: str) -> list[dict[str, Any]]:
    episodes: list[dict[str, Any]] = _get(base, key, f"/vehicles/{vehicle}/faults?code=OFFLINE")[
        "episodes"
    ]
    return episodes


def test_a_restart_with_a_bus_unreachable_does_not_page_its_unit(tmp_path: Path) -> None:
    db = tmp_path / "eqgw.db"
    started: list[Process] = []  # each stopped at the end, whatever failed
    try:
        sim_a, port_a = _simulator(tmp_path)
        started.append(sim_a)
        sim_b, port_b = _simulator(tmp_path)
        started.append(sim_b)
        fleet = _fleet(tmp_path / "fleet.toml", {"A": port_a, "B": port_b})
        gw, base = _gateway(tmp_path, db, fleet)
        started.append(gw)
        key = ADMIN_KEY.search(gw.output())
        assert key, gw.output()
        admin = key.group(1)
        wait_until(lambda: _online(base, admin) == {"A": True, "B": True}, 60, "both units online")
        b_heard = _last_seen(base, admin, "B")
        assert gw.stop() in CLEAN_EXIT, gw.output()[-3000:]
        # B's bus is gone while the gateway is down, for longer than the offline window after
        # the last frame the gateway had of B.
        sim_b.stop()
        wait_until(lambda: time.time() > b_heard + OFFLINE_AFTER_S + 1, 30, "B silent a window")
        gw, base = _gateway(tmp_path, db, fleet)
        started.append(gw)
        wait_until(lambda: _online(base, admin).get("A"), 60, "A online after the restart")
        # Two offline windows with B's bus connecting and A's unit talking: A heard two
        # windows after it was first heard again.
        back = _last_seen(base, admin, "A")
        wait_until(
            lambda: _last_seen(base, admin, "A") >= back + 2 * OFFLINE_AFTER_S,
            60,
            "A heard for two offline windows",
            interval=0.2,
        )
        assert _offline_episodes(base, admin, "B") == []
        assert _offline_episodes(base, admin, "A") == []
        # B's bus is back: its unit is heard and online, never paged.
        sim_b, _ = _simulator(tmp_path, port_b)
        started.append(sim_b)
        wait_until(lambda: _online(base, admin) == {"A": True, "B": True}, 60, "B online again")
        assert _offline_episodes(base, admin, "B") == []
        assert gw.stop() in CLEAN_EXIT, gw.output()[-3000:]
    finally:
        for proc in started:
            if proc.proc.poll() is None:
                proc.stop()
