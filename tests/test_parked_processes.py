"""An evening at the depot with real processes: `eqgw simulate --scenario ignition-off` serves
three coaches over socketcand and `eqgw serve` reads them. Two coaches are switched off (the
whole bus silent) and on again: parked, never paged. The third loses one unit's wiring while
its partner talks on: that unit is offline, the evening's only alert."""

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
CLEAN_EXIT = (0, -signal.SIGTERM)
# Simulated seconds per real second. The simulator starts once the gateway reads every bus
# (--start-on-connect); the scenario switches off at 1 min (6 s later), cuts LATE-03's unit at
# 90 s for 1 min and switches on again at 3 min (18 s).
SPEED = 10
UNITS = {"EVENING-01": [30], "EVENING-02": [30, 31], "LATE-03": [30, 31]}


def _fleet(path: Path, port: int) -> Path:
    lines = []
    for vehicle, sas in UNITS.items():
        lines.append(f'[[vehicles]]\nid = "{vehicle}"\n')
        lines.append(
            f'[[buses]]\nname = "{vehicle}/can0"\nvehicle_id = "{vehicle}"\n'
            f'interface = "socketcand"\nchannel = "{vehicle}"\nequalizer_sas = {sas}\n'
            f'options = {{ host = "127.0.0.1", port = {port} }}\n'
        )
    path.write_text("\n".join(lines))
    return path


def _get(base: str, key: str, path: str) -> Any:
    r = web.get(f"{base}/api/v1{path}", headers={"Authorization": f"Bearer {key}"}, timeout=10)
    assert r.status_code == 200, r.text
    return r.json()


def test_parked_coaches_page_nobody_and_an_offline_unit_does(tmp_path: Path) -> None:
    sim = Process(
        eqgw("simulate", "--scenario", "ignition-off", "--speed", str(SPEED),
             "--listen", "127.0.0.1:0", "--start-on-connect"),
        tmp_path,
    )  # fmt: skip
    gw: Process | None = None
    try:
        port = int(sim.wait_line(LISTENING).group(2))
        api_port = free_port()
        env = {
            "EQGW_DATABASE_URL": f"sqlite:///{tmp_path / 'eqgw.db'}",
            "EQGW_API_PORT": str(api_port),
        }
        gw = Process(eqgw("serve", "--config", str(_fleet(tmp_path / "fleet.toml", port))),
                     tmp_path, env)  # fmt: skip
        gw.wait_line(SERVING, timeout=120)
        sim.wait_line(re.compile("the simulation starts"), timeout=60)
        started = time.monotonic()
        key = ADMIN_KEY.search(gw.output())
        assert key, gw.output()
        admin, base = key.group(1), f"http://127.0.0.1:{api_port}"
        history: list[dict[str, str]] = []

        def vehicles() -> dict[str, dict[str, Any]]:
            listing = {v["id"]: v for v in _get(base, admin, "/vehicles")["vehicles"]}
            history.append({vid: v["state"] for vid, v in listing.items()})
            return listing

        def every_unit_online() -> bool:
            v = vehicles()
            return all(
                sorted(u["unit"] for u in v[vid]["units"] if u["online"]) == sas
                for vid, sas in UNITS.items()
            )

        wait_until(every_unit_online, 60, "every unit heard")
        # Until then a coach whose units are not all heard yet is listed not reporting.
        del history[:-1]
        up = time.monotonic() - started
        assert up < 60 / SPEED, f"the gateway heard every unit {up:.1f} s after the start"

        def parked() -> dict[str, Any] | None:
            v = vehicles()
            both = all(v[vid]["state"] == "parked" for vid in ("EVENING-01", "EVENING-02"))
            return v if both else None

        mid = wait_until(parked, 60, "both evening coaches parked")
        for vid in ("EVENING-01", "EVENING-02"):
            assert mid[vid]["parked_since"] and mid[vid]["last_heard"]
            assert {u["state"] for u in mid[vid]["units"]} == {"parked"}
            assert mid[vid]["online"] is False
        wait_until(lambda: vehicles()["LATE-03"]["state"] == "offline", 60, "LATE-03 offline")

        def all_ok() -> bool:
            v = vehicles()
            return all(v[vid]["state"] == "ok" for vid in UNITS) and every_unit_online()

        wait_until(all_ok, 60, "every coach reporting again")
        # The states each coach went through, as the listing showed them.
        for vid, expected in (
            ("EVENING-01", ["ok", "parked", "ok"]),
            ("EVENING-02", ["ok", "parked", "ok"]),
            ("LATE-03", ["ok", "offline", "ok"]),
        ):
            seen = [h[vid] for h in history]
            assert [s for i, s in enumerate(seen) if i == 0 or seen[i - 1] != s] == expected, (
                vid,
                seen,
            )

        def cleared() -> list[dict[str, Any]] | None:
            alerts: list[dict[str, Any]] = _get(base, admin, "/alerts?limit=100")["alerts"]
            return alerts if alerts and all(a["state"] == "cleared" for a in alerts) else None

        alerts = wait_until(cleared, 60, "the offline alert cleared")
        assert [(a["vehicle_id"], a["sa"], a["rule"]) for a in alerts] == [
            ("LATE-03", 31, "offline")
        ]
        for vid in ("EVENING-01", "EVENING-02"):
            assert _get(base, admin, f"/vehicles/{vid}/faults?code=OFFLINE")["episodes"] == []
        assert gw.stop() in CLEAN_EXIT, gw.output()[-3000:]
    finally:
        for proc in (gw, sim):
            if proc is not None and proc.proc.poll() is None:
                proc.stop()
