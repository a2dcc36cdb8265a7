"""A unit the gateway already knew at its start, without a series, is asked for its IDs too:
no unit-online event ever comes for it (it is in the live state from the first frame on), so
only the identifier's scan of the live state finds it. Real processes: `eqgw replay` puts the
unit in the database without a series (the log has no identification), then `eqgw serve`
reads the unit's bus from an `eqgw simulate` socketcand server."""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

from eqgw.protocol.encode import encode
from tests.cluster_helpers import LISTENING
from tests.proc_helpers import Process, eqgw, free_port, wait_until
from tests.support import web

SERVING = re.compile(r"serving on")
ADMIN_KEY = re.compile(r"^\s+(eqgw_\S+)\s*$", re.M)


def _log(path: Path) -> Path:
    """A candump -L log of one unit (SA 30) saying its status, never its IDs."""
    lines = []
    for i in range(5):
        for can_id, data in encode("status", {}, sa=30):
            lines.append(f"(1700000000.{i:06d}) can0 {can_id:08X}#{data.hex().upper()}")
    path.write_text("\n".join(lines) + "\n")
    return path


def test_a_unit_known_before_the_start_is_identified(tmp_path: Path) -> None:
    sim = Process(
        eqgw("simulate", "--vehicles", "1", "--listen", "127.0.0.1:0", "--seed", "3"), tmp_path
    )
    gw: Process | None = None
    try:
        sim_port = int(sim.wait_line(LISTENING).group(2))
        fleet = tmp_path / "fleet.toml"
        fleet.write_text(
            '[[vehicles]]\nid = "A"\n\n[[buses]]\nname = "A/can0"\nvehicle_id = "A"\n'
            'interface = "socketcand"\nchannel = "SIM-001"\n'
            f'options = {{ host = "127.0.0.1", port = {sim_port} }}\n'
        )
        db = f"sqlite:///{tmp_path / 'eqgw.db'}"
        log = str(_log(tmp_path / "a.log"))
        args = ["replay", log, "--vehicle", "A", "--config", str(fleet), "--db", db, "--quiet"]
        replay = Process(eqgw(*args), tmp_path)
        replay.proc.wait(timeout=120)
        assert replay.stop() == 0, replay.output()
        port = free_port()
        gw = Process(
            eqgw("serve", "--config", str(fleet)),
            tmp_path,
            {"EQGW_DATABASE_URL": db, "EQGW_API_PORT": str(port)},
        )
        gw.wait_line(SERVING, timeout=120)
        key = ADMIN_KEY.search(gw.output())
        assert key, gw.output()
        base, auth = f"http://127.0.0.1:{port}", {"Authorization": f"Bearer {key.group(1)}"}

        def unit() -> dict[str, Any]:
            r = web.get(f"{base}/api/v1/vehicles", headers=auth, timeout=10)
            assert r.status_code == 200, r.text
            units: list[dict[str, Any]] = [u for v in r.json()["vehicles"] for u in v["units"]]
            assert len(units) == 1, units  # the unit of the replay, heard live again
            return units[0]

        wait_until(lambda: unit()["online"], 60, "the unit heard on its live bus")
        # The simulated SIM-001 is an 80-series unit: it says so once asked.
        wait_until(lambda: unit()["series"] == 80, 60, "the unit's series learned")
    finally:
        for proc in (gw, sim):
            if proc is not None and proc.proc.poll() is None:
                proc.stop()
