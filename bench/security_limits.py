"""What abusive clients cost a running gateway: its resident memory before and after.

Starts `eqgw serve --simulate 1` on a temporary SQLite file, then
1. four clients at once each POST a 200 MB body without a key (streamed, Content-Length set);
2. a viewer's websocket sends 1,000 subscribe messages a second for 10 s without reading;
3. one key opens 450 websockets from one address, each reading, while another client asks
   `GET /api/v1/vehicles` every 0.2 s;
and prints the process's VmRSS after each, with how each client was answered (3: how many
sockets were refused, and the slowest answer to the other client).

    PYTHONPATH=. python bench/security_limits.py [--unbounded] [--vehicles N]

`--unbounded` raises the bounds on open websockets (EQGW_API_WS_MAX_PER_KEY,
EQGW_API_WS_MAX_PER_CLIENT) to 10,000, to see what step 3 costs without them; `--vehicles`
simulates N vehicles instead of 1 (every socket is sent every vehicle's events).
"""

from __future__ import annotations

import asyncio
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


SOCKETS = 450


async def many_websockets(host: str, port: int, key: str) -> str:
    """SOCKETS websockets of one key, each reading, while another client polls the API."""
    import httpx
    from websockets.asyncio.client import connect

    url = f"ws://{host}:{port}/api/v1/ws"
    headers = {"Authorization": f"Bearer {key}"}
    outcomes: dict[str, int] = {}
    stop = asyncio.Event()

    async def one() -> None:
        try:
            async with connect(url, additional_headers=headers, open_timeout=60) as ws:
                first = await ws.recv()
                outcome = "refused" if '"error"' in str(first)[:20] else "open"
                outcomes[outcome] = outcomes.get(outcome, 0) + 1
                if outcome == "open":
                    async for _ in ws:  # read everything until told to stop
                        if stop.is_set():
                            break
        except Exception as exc:
            name = f"failed ({type(exc).__name__})"
            outcomes[name] = outcomes.get(name, 0) + 1

    slowest = 0.0
    async with httpx.AsyncClient(base_url=f"http://{host}:{port}", timeout=120) as client:
        tasks = [asyncio.create_task(one()) for _ in range(SOCKETS)]
        end = time.monotonic() + 20
        while time.monotonic() < end:
            start = time.monotonic()
            r = await client.get("/api/v1/vehicles", headers=headers)
            r.raise_for_status()
            slowest = max(slowest, time.monotonic() - start)
            await asyncio.sleep(0.2)
        stop.set()
        for t in tasks:
            t.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)
        refused = [
            ln for ln in (await client.get("/metrics")).text.splitlines()
            if ln.startswith("eqgw_ws_refused_total")
        ]  # fmt: skip
    counts = ", ".join(f"{n} {what}" for what, n in sorted(outcomes.items()))
    return (
        f"{SOCKETS} websockets of one key: {counts}; slowest GET /api/v1/vehicles meanwhile "
        f"{slowest:.2f} s; {'; '.join(refused)}"
    )


def main() -> int:
    with tempfile.TemporaryDirectory() as tmp:
        env = {k: v for k, v in os.environ.items() if not k.startswith("EQGW_")}
        env.update(
            EQGW_DATABASE_URL=f"sqlite:///{tmp}/eqgw.db",
            PYTHONPATH=str(ROOT),
            PYTHONUNBUFFERED="1",
        )
        args = sys.argv[1:]
        vehicles = args[args.index("--vehicles") + 1] if "--vehicles" in args else "1"
        if "--unbounded" in args:
            env.update(EQGW_API_WS_MAX_PER_KEY="10000", EQGW_API_WS_MAX_PER_CLIENT="10000")
        proc = subprocess.Popen(
            [sys.executable, "-m", "eqgw.cli", "serve", "--simulate", vehicles, "--port", "0"],
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
            line = asyncio.run(many_websockets(host, port, key_m.group(1)))
            print(f"{line}; {rss_mb(proc.pid):.0f} MB resident")
        finally:
            proc.terminate()
            proc.wait(30)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
