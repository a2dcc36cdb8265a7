"""`eqgw serve` as a user runs it: the first start prints an admin key once, never again."""

from __future__ import annotations

import os
import queue
import re
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import httpx

from tests.proc_helpers import terminate

KEY = re.compile(r"\beqgw_[A-Za-z0-9_-]{20,}")
SERVING = re.compile(r"serving on (http://\S+)")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port: int = s.getsockname()[1]
        return port


@contextmanager
def _serve(tmp_path: Path, port: int) -> Iterator[tuple[list[str], queue.Queue[str]]]:
    """`eqgw serve --simulate 1` in a subprocess; yields a list for lines seen and a line queue."""
    env = {
        **os.environ,
        "EQGW_DATABASE_URL": f"sqlite:///{tmp_path / 'eqgw.db'}",
        "EQGW_API_PORT": str(port),
        "PYTHONUNBUFFERED": "1",
    }
    env.pop("EQGW_CONFIG", None)
    proc = subprocess.Popen(
        [sys.executable, "-m", "app.cli", "serve", "--simulate", "1"],
        cwd=tmp_path,
        env={**env, "PYTHONPATH": str(Path(__file__).resolve().parents[1])},
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    lines: queue.Queue[str] = queue.Queue()

    def pump() -> None:
        assert proc.stdout is not None
        for line in proc.stdout:
            lines.put(line)

    reader = threading.Thread(target=pump, daemon=True)
    reader.start()
    try:
        yield [], lines
    finally:
        terminate(proc)
        reader.join(timeout=10)
        assert proc.stdout is not None
        proc.stdout.close()


def _until_ready(port: int, lines: queue.Queue[str], seen: list[str], timeout: float = 60) -> None:
    """Collect output until the server answers /healthz (the key, if any, is printed before)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        try:
            while True:
                seen.append(lines.get_nowait())
        except queue.Empty:
            pass
        try:
            if httpx.get(f"http://127.0.0.1:{port}/healthz", timeout=2).status_code == 200:
                while not lines.empty():
                    seen.append(lines.get_nowait())
                return
        except httpx.TransportError:
            time.sleep(0.2)
    raise AssertionError("eqgw serve did not come up:\n" + "".join(seen))


def test_first_start_prints_the_admin_key_once(tmp_path: Path) -> None:
    port = _free_port()
    with _serve(tmp_path, port) as (seen, lines):
        _until_ready(port, lines, seen)
        out = "".join(seen)
        keys = set(KEY.findall(out))
        assert len(keys) == 1, out
        (key,) = keys
        # The key on its own line, then the login URL carrying it; both exactly once.
        assert out.count(f"    {key}\n") == 1, out
        assert out.count(f"open http://127.0.0.1:{port}/?key={key}") == 1, out
        r = httpx.get(
            f"http://127.0.0.1:{port}/api/v1/vehicles",
            headers={"Authorization": f"Bearer {key}"},
            timeout=10,
        )
        assert r.status_code == 200, r.text
        assert [v["id"] for v in r.json()["vehicles"]] == ["SIM-001"]

    port = _free_port()
    with _serve(tmp_path, port) as (seen, lines):
        _until_ready(port, lines, seen)
        out = "".join(seen)
        assert SERVING.search(out), out
        assert not KEY.search(out) and "?key=" not in out, out
        # The key printed the first time still works against the same database.
        r = httpx.get(
            f"http://127.0.0.1:{port}/api/v1/vehicles",
            headers={"Authorization": f"Bearer {key}"},
            timeout=10,
        )
        assert r.status_code == 200, r.text
