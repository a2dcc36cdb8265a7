"""A socketcand link that stops draining: `eqgw simulate` frozen with SIGSTOP (its TCP connection
open, its kernel still taking bytes), `eqgw serve` delivering a command to it.

The gateway must stop handing frames to the link within its `stall_after_s`, say so in /readyz and
/metrics, and end the command `unconfirmed` (frames left, none confirmed), never `failed`: once the
simulator resumes, exactly the frames the gateway counted arrive, late, and may take effect.
"""

from __future__ import annotations

import os
import re
import signal
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import can
import pytest

from tests.proc_helpers import Process, eqgw, free_port, wait_until
from tests.support import web

KEY = re.compile(r"\beqgw_[A-Za-z0-9_-]{20,}")
LISTENING = re.compile(r"listening 127\.0\.0\.1:(\d+)")
CONTROL_PGN = 0xFFD2  # 65490, sent by the gateway only
GATEWAY_SA = 0xD8
REQUEST_PGN = 0xEA00  # 59904


class ControlFrames:
    """Control frames from the gateway seen on the simulator's bus, by a second socketcand
    client (the simulator's virtual bus hands it what the gateway sent)."""

    def __init__(self, port: int, channel: str) -> None:
        self.bus = can.Bus(interface="socketcand", host="127.0.0.1", port=port, channel=channel)
        self.seen: list[float] = []
        self.dm1_requests = 0  # requests for DM1 the gateway sent (PGN 59904, `CA FE 00`)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            msg = self.bus.recv(0.2)
            if msg is None:
                continue
            pgn = (msg.arbitration_id >> 8) & 0xFFFF
            if msg.arbitration_id & 0xFF != GATEWAY_SA:
                continue
            if pgn == CONTROL_PGN:
                self.seen.append(time.monotonic())
            elif pgn & 0xFF00 == REQUEST_PGN and bytes(msg.data[:3]) == b"\xca\xfe\x00":
                self.dm1_requests += 1

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5)
        self.bus.shutdown()


@pytest.fixture
def simulator(tmp_path: Path) -> Iterator[tuple[Process, int]]:
    sim = Process(
        eqgw("simulate", "--vehicles", "1", "--listen", "127.0.0.1:0", "--seed", "1"), tmp_path
    )
    try:
        port = int(sim.wait_line(LISTENING).group(1))
        yield sim, port
    finally:
        if sim.proc.poll() is None:
            os.kill(sim.proc.pid, signal.SIGCONT)
        sim.stop()


def _fleet(tmp_path: Path, port: int) -> Path:
    path = tmp_path / "fleet.toml"
    path.write_text(
        '[[vehicles]]\nid = "SIM-001"\n\n'
        '[[buses]]\nname = "SIM-001/sim"\nvehicle_id = "SIM-001"\ninterface = "socketcand"\n'
        f'channel = "SIM-001"\noptions = {{ host = "127.0.0.1", port = {port} }}\n'
    )
    return path


def _metric(text: str, name: str) -> float:
    m = re.search(rf"^{name}(?:{{[^}}]*}})? (\S+)$", text, re.M)
    assert m, f"{name} not in /metrics"
    return float(m.group(1))


@pytest.mark.timeout(180)
def test_a_stalled_link_is_not_fed_and_the_command_ends_unconfirmed(
    tmp_path: Path, simulator: tuple[Process, int]
) -> None:
    sim, sim_port = simulator
    port = free_port()
    env = {"EQGW_DATABASE_URL": f"sqlite:///{tmp_path / 'eqgw.db'}"}
    gw = Process(
        eqgw("serve", "--config", str(_fleet(tmp_path, sim_port)), "--port", str(port)),
        tmp_path,
        env,
    )
    watcher = ControlFrames(sim_port, "SIM-001")
    try:
        gw.wait_line(re.compile(r"serving on"))
        m = KEY.search(gw.output())
        assert m, gw.output()
        auth = {"Authorization": f"Bearer {m.group(0)}"}
        base = f"http://127.0.0.1:{port}"
        api = f"{base}/api/v1"
        with web.Client(timeout=10) as http:

            def online() -> bool:
                r = http.get(f"{api}/vehicles/SIM-001/live", headers=auth)
                units = r.json()["units"] if r.status_code == 200 else []
                return any(u.get("status_flags") for u in units)

            wait_until(online, 60, "the simulated unit online through socketcand")
            ready = http.get(f"{base}/readyz", headers=auth)
            assert ready.status_code == 200 and ready.json()["buses"][0]["stalled"] is False

            os.kill(sim.proc.pid, signal.SIGSTOP)  # frozen: its socket still takes bytes
            stopped_at = time.monotonic()
            r = http.post(
                f"{api}/vehicles/SIM-001/commands",
                json={"jump_start_override": True, "expires_in_s": 12},
                headers=auth,
            )
            assert r.status_code == 202, r.text
            cid = r.json()["id"]

            def stalled() -> dict[str, Any] | None:
                r = http.get(f"{base}/readyz", headers=auth)
                bus = r.json()["buses"][0]
                return r.json() if r.status_code == 503 and bus["stalled"] else None

            body = wait_until(stalled, 30, "/readyz to report the link stalled")
            assert "stalled" in body["buses"][0]["last_error"]
            metrics = http.get(f"{base}/metrics", headers=auth).text
            assert _metric(metrics, "eqgw_bus_stalled") == 1.0

            def ended() -> dict[str, Any] | None:
                got: dict[str, Any] = http.get(f"{api}/commands/{cid}", headers=auth).json()
                return got if got["state"] not in ("queued", "sending") else None

            cmd = wait_until(ended, 60, "the command's end")
            # Frames left the gateway, none was confirmed: not "failed".
            assert cmd["state"] == "unconfirmed", cmd
            assert "may still take effect" in cmd["reason"]
            handed = cmd["sends"]
            # The link is given up on within its stall_after_s (4 s) of silence, at 1 frame/s:
            # not the 12 frames of the command's whole life.
            assert 1 <= handed <= 6, cmd
            metrics = http.get(f"{base}/metrics", headers=auth).text
            frames_handed = _metric(metrics, "eqgw_bus_frames_handed_total")
            audit = http.get(f"{api}/audit", headers=auth).json()["entries"]
            outcomes = [e["outcome"] for e in audit if e["command_id"] == cid]
            assert sorted(outcomes) == ["accepted", "unconfirmed"], outcomes
            assert watcher.seen == []  # nothing passed the frozen simulator

            os.kill(sim.proc.pid, signal.SIGCONT)
            resumed_at = time.monotonic()
            wait_until(lambda: len(watcher.seen) >= handed, 30, "the held frames to arrive late")
            wait_until(
                lambda: http.get(f"{base}/readyz", headers=auth).status_code == 200,
                30,
                "ready again",
            )
            # Anything else still on its way arrives before a frame the gateway sends now: one
            # link, in order. A DM1 request is that frame (the gateway sends none of its own).
            requests = watcher.dm1_requests
            r = http.post(
                f"{api}/vehicles/SIM-001/requests",
                json={"unit": 30, "what": "dm1", "expires_in_s": 5},
                headers=auth,
            )
            assert r.status_code == 202, r.text
            wait_until(lambda: watcher.dm1_requests > requests, 30, "a frame sent after all")
            # Exactly what the gateway counted as handed over arrived, all after the resume.
            assert len(watcher.seen) == handed
            assert all(t >= resumed_at for t in watcher.seen)
            assert frames_handed >= handed  # the identification requests count there too
            assert http.get(f"{base}/readyz", headers=auth).json()["buses"][0]["stalled"] is False
            assert stopped_at < resumed_at
    finally:
        watcher.close()
        gw.stop()
