"""What abusive clients cost a running gateway: its resident memory before and after.

Starts `eqgw serve --simulate 1` on a temporary SQLite file, then
1. four clients at once each POST a 200 MB body without a key (streamed, Content-Length set);
2. a viewer's websocket sends 1,000 subscribe messages a second for 10 s without reading;
and prints the process's VmRSS after each, with how each client was answered.

    PYTHONPATH=. python bench/security_limits.py
"""

from __future__ import annotations

import os
import re
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

from websockets.exceptions import ConnectionClosed
from websockets.sync.client import connect as ws_connect

ROOT = Path(__file__).resolve().parent.parent
BODY = 200 * 1024 * 1024
SERVING = re.compile(r"serving on http://([\d.]+):(\d+)")
KEY = re.compile(r"^\s+(eqgw_\S+)$", re.M)


def rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def post_unauthenticated(host: str, port: int, out: list[str]) -> None:
    chunk = b" " * (1024 * 1024)
    try:
        with socket.create_connection((host, port), timeout=60) as sock:
            sock.sendall(
                b"POST /api/v1/vehicles/SIM-001/commands HTTP/1.1\r\nHost: x\r\n"
                b"Content-Type: application/json\r\n" + f"Content-Length: {BODY}\r\n\r\n".encode()
            )
            sent = 0
            try:
                while sent < BODY:
                    sock.sendall(chunk)
                    sent += len(chunk)
            except OSError:
                pass  # the server answered and closed before the body was through
            reply = sock.recv(200).split(b"\r\n", 1)[0].decode(errors="replace")
            out.append(f"{reply or 'no reply'} after {sent // (1024 * 1024)} MB sent")
    except OSError as exc:
        out.append(f"error: {exc}")


def main() -> int:
    with tempfile.TemporaryDirectory() as tmp:
        env = {k: v for k, v in os.environ.items() if not k.startswith("EQGW_")}
        env.update(
            EQGW_DATABASE_URL=f"sqlite:///{tmp}/eqgw.db",
            PYTHONPATH=str(ROOT),
            PYTHONUNBUFFERED="1",
        )
        proc = subprocess.Popen(
            [sys.executable, "-m", "eqgw.cli", "serve", "--simulate", "1", "--port", "0"],
            cwd=tmp, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
        )  # fmt: skip
        assert proc.stdout is not None
        lines: list[str] = []
        try:
            while not (m := SERVING.search("".join(lines))):
                line = proc.stdout.readline()
                if not line:
                    print("".join(lines))
                    return 1
                lines.append(line)
            threading.Thread(target=lambda: [None for _ in proc.stdout], daemon=True).start()  # type: ignore[union-attr]
            host, port = m.group(1), int(m.group(2))
            key_m = KEY.search("".join(lines))
            assert key_m is not None
            time.sleep(3)
            print(f"idle: {rss_mb(proc.pid):.0f} MB resident")

            answers: list[str] = []
            threads = [
                threading.Thread(target=post_unauthenticated, args=(host, port, answers))
                for _ in range(4)
            ]
            for t in threads:
                t.start()
            for t in threads:
                t.join(300)
            print(f"after 4 unauthenticated 200 MB bodies: {rss_mb(proc.pid):.0f} MB resident")
            for a in answers:
                print(f"    {a}")

            url = f"ws://{host}:{port}/api/v1/ws?vehicles=SIM-001"
            headers = {"Authorization": f"Bearer {key_m.group(1)}"}
            sent = 0
            outcome = "still open after 10 s"
            with ws_connect(url, additional_headers=headers, open_timeout=20) as ws:
                ws.recv(timeout=20)
                start = time.monotonic()
                try:
                    while time.monotonic() - start < 10:
                        for _ in range(100):
                            ws.send('{"type": "subscribe", "vehicles": ["SIM-001"]}')
                            sent += 1
                        time.sleep(0.1)
                except ConnectionClosed:
                    pass
                try:
                    while True:
                        ws.recv(timeout=5)
                except ConnectionClosed:
                    outcome = f"closed {ws.close_code} ({ws.close_reason})"
                except TimeoutError:
                    pass
            print(
                f"after a websocket sent {sent} subscribe messages: "
                f"{rss_mb(proc.pid):.0f} MB resident; {outcome}"
            )
        finally:
            proc.terminate()
            proc.wait(30)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
