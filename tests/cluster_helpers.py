"""Real `eqgw simulate` and `eqgw serve` subprocesses for the several-gateways tests."""

from __future__ import annotations

import os
import queue
import re
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import httpx

ROOT = Path(__file__).resolve().parents[1]
LISTENING = re.compile(r"listening (\S+):(\d+)")


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port: int = s.getsockname()[1]
        return port


class Proc:
    """A child process whose output lines are collected on a thread."""

    def __init__(self, args: list[str], env: dict[str, str], cwd: Path) -> None:
        self.args = args
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "app.cli", *args],
            cwd=cwd,
            env={**env, "PYTHONPATH": str(ROOT), "PYTHONUNBUFFERED": "1"},
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
        )
        self.lines: queue.Queue[str] = queue.Queue()
        self.seen: list[str] = []
        self._pump = threading.Thread(target=self._read, daemon=True)
        self._pump.start()

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            self.lines.put(line)

    def wait_line(self, pattern: re.Pattern[str], timeout: float = 60) -> re.Match[str]:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            try:
                line = self.lines.get(timeout=0.2)
            except queue.Empty:
                if self.proc.poll() is not None:
                    break
                continue
            self.seen.append(line)
            m = pattern.search(line)
            if m:
                return m
        raise AssertionError(f"{self.args[0]}: no {pattern.pattern!r} in {self.seen[-30:]}")

    def output(self) -> str:
        while True:
            try:
                self.seen.append(self.lines.get_nowait())
            except queue.Empty:
                return "".join(self.seen)

    def kill(self) -> None:
        """SIGKILL: no shutdown code runs, the sockets close with the process."""
        self.proc.send_signal(signal.SIGKILL)
        self.proc.wait(timeout=10)

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(timeout=30)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(timeout=10)
        self._pump.join(timeout=10)
        assert self.proc.stdout is not None
        self.proc.stdout.close()


def start_simulator(tmp_path: Path, vehicles: int, *extra: str) -> tuple[Proc, int]:
    env = {k: v for k, v in os.environ.items() if not k.startswith("EQGW_")}
    sim = Proc(
        ["simulate", "--vehicles", str(vehicles), "--listen", "127.0.0.1:0", *extra], env, tmp_path
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
) -> tuple[Proc, str]:
    port = free_port()
    env = {k: v for k, v in os.environ.items() if not k.startswith("EQGW_")}
    env.update(
        {
            "EQGW_DATABASE_URL": db_url,
            "EQGW_API_PORT": str(port),
            "EQGW_CLUSTER_INSTANCE_ID": instance,
            "EQGW_CLUSTER_LEASE_PERIOD_S": str(lease_period_s),
            "EQGW_CLUSTER_LEASE_TIMEOUT_S": "2",
            **(extra_env or {}),
        }
    )
    proc = Proc(["serve", "--config", str(fleet)], env, tmp_path)
    return proc, f"http://127.0.0.1:{port}"


def readyz(base: str) -> dict[str, Any] | None:
    try:
        r = httpx.get(f"{base}/readyz", timeout=5)
    except httpx.HTTPError:
        return None
    body: dict[str, Any] = r.json()
    return body


def wait_for(check: Callable[[], Any], timeout: float, what: str, interval: float = 0.2) -> Any:
    """Poll `check` until it returns something truthy; fail with `what` after `timeout`."""
    deadline = time.monotonic() + timeout
    last: Any = None
    while time.monotonic() < deadline:
        last = check()
        if last:
            return last
        time.sleep(interval)
    raise AssertionError(f"timed out after {timeout:g} s waiting for {what} (last: {last!r})")
