"""Benchmark: frames/s one gateway process receives from socketcand buses, beside bare python-can.

Each phase gets a fresh server subprocess serving N buses. Phase "bare" reads every bus with
python-can's socketcand client in a `bus.recv()` loop (one thread per bus, nothing else); phase
"gateway" reads them with eqgw's BusReader and one `async for` consumer task per bus, as the
ingest does.

Sources (--source):
- blast (default): a minimal socketcand server in this file that answers the handshake and then
  writes pre-formatted frame lines as fast as TCP takes them. It costs almost no CPU, so the
  receiving process is the bottleneck and its rate is its capacity.
- eqgw: `python -m eqgw.bus.socketcand_server --generate`, the simulator's real path (virtual
  bus, per-client endpoint). On a small machine that server saturates first; the receiving
  rates are then lower bounds and the CPU-normalised figures say more.

    python bench/bus_receive.py                       # 4 buses, blast source, 8 s per phase
    python bench/bus_receive.py --source eqgw --rate 5000
"""

from __future__ import annotations

import argparse
import asyncio
import json
import logging
import os
import signal
import socket
import socketserver
import subprocess
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import can

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from eqgw.bus.config import BusConfig  # noqa: E402
from eqgw.bus.log_filters import install_socketcand_log_filter  # noqa: E402
from eqgw.bus.reader import BusReader  # noqa: E402

FULL_BUS_FPS = 1900  # 250 kbit/s, 29-bit identifiers, 8 data bytes, 100 % load


@dataclass
class Phase:
    """What one phase measured."""

    name: str
    frames: int
    seconds: float
    cpu_seconds: float
    client_drops: int
    server: dict[str, Any]

    @property
    def rate(self) -> float:
        return self.frames / self.seconds

    @property
    def per_cpu_second(self) -> float:
        # Frames per second of this process's CPU time (all threads): the cost per frame,
        # independent of whether the source or the receiver was the bottleneck.
        return self.frames / self.cpu_seconds if self.cpu_seconds > 0 else 0.0


class BlastHandler(socketserver.BaseRequestHandler):
    """One client of the blast server: handshake, then frame lines until it hangs up."""

    def handle(self) -> None:
        sock: socket.socket = self.request
        stamp = f"{time.time():.6f}"
        lines = (f"< frame 18FF001E {stamp} {i:08X}FFFFFFFF >" for i in range(1000))
        block = "".join(lines).encode()
        try:
            sock.sendall(b"< hi >")
            for reply in (b"< ok >", b"< ok >"):  # open NAME, rawmode
                if not sock.recv(256):
                    return
                sock.sendall(reply)
            # python-can reads the rawmode `< ok >` with one recv(); frames must not join it.
            time.sleep(0.2)
            while True:
                sock.sendall(block)
        except OSError:
            return


def serve_blast() -> int:
    """Run the blast server until killed (the subprocess side of --source blast)."""
    socketserver.ThreadingTCPServer.daemon_threads = True
    socketserver.ThreadingTCPServer.allow_reuse_address = True
    with socketserver.ThreadingTCPServer(("127.0.0.1", 0), BlastHandler) as server:
        print(f"listening 127.0.0.1:{server.server_address[1]}", flush=True)
        server.serve_forever()
    return 0


class Server:
    """The frame source subprocess for one phase."""

    def __init__(self, source: str, buses: int, rate: str) -> None:
        if source == "blast":
            args = [sys.executable, __file__, "--serve-blast"]
        else:
            args = [sys.executable, "-m", "eqgw.bus.socketcand_server", "--listen", "127.0.0.1:0"]
            args += ["--log-level", "WARNING"]
            for i in range(buses):
                args += ["--bus", f"BENCH-{i}=bench-{i}", "--generate", f"BENCH-{i}:{rate}"]
        self.source = source
        self.proc = subprocess.Popen(args, cwd=REPO, stdout=subprocess.PIPE, text=True)
        assert self.proc.stdout is not None
        line = self.proc.stdout.readline()
        if not line.startswith("listening"):
            self.proc.kill()
            raise SystemExit(f"server did not start: {line!r}")
        self.port = int(line.split()[1].rsplit(":", 1)[1])
        self.names = [f"BENCH-{i}" for i in range(buses)]

    def stop(self) -> dict[str, Any]:
        self.proc.send_signal(signal.SIGTERM if self.source == "eqgw" else signal.SIGKILL)
        out, _ = self.proc.communicate(timeout=30)
        lines = out.strip().splitlines()
        return dict(json.loads(lines[-1])) if lines else {}


def measure_bare(names: list[str], port: int, warmup: float, seconds: float) -> Phase:
    """python-can's socketcand client, nothing but recv() in a loop."""
    counts = [0] * len(names)
    stop = threading.Event()
    buses = [
        can.Bus(interface="socketcand", channel=name, host="127.0.0.1", port=port) for name in names
    ]

    def receive(i: int) -> None:
        bus = buses[i]
        while not stop.is_set():
            if bus.recv(0.5) is not None:
                counts[i] += 1

    threads = [threading.Thread(target=receive, args=(i,)) for i in range(len(names))]
    for thread in threads:
        thread.start()
    time.sleep(warmup)
    start, cpu_start, before = time.monotonic(), time.process_time(), sum(counts)
    time.sleep(seconds)
    frames = sum(counts) - before
    elapsed, cpu = time.monotonic() - start, time.process_time() - cpu_start
    stop.set()
    for thread in threads:
        thread.join()
    for bus in buses:
        bus.shutdown()
    return Phase("bare", frames, elapsed, cpu, 0, {})


async def measure_gateway(
    names: list[str], port: int, warmup: float, seconds: float, queue_size: int
) -> Phase:
    """eqgw's BusReader per bus, one `async for` consumer each."""
    counts = [0] * len(names)
    readers = [
        BusReader(
            BusConfig(
                name=f"{name}/can0",
                vehicle_id=name,
                interface="socketcand",
                channel=name,
                options={"host": "127.0.0.1", "port": port},
            ),
            queue_size=queue_size,
        )
        for name in names
    ]

    async def consume(i: int) -> None:
        async for _msg in readers[i]:
            counts[i] += 1

    for reader in readers:
        await reader.start()
    consumers = [asyncio.create_task(consume(i)) for i in range(len(names))]
    await asyncio.sleep(warmup)
    start, cpu_start, before = time.monotonic(), time.process_time(), sum(counts)
    await asyncio.sleep(seconds)
    frames = sum(counts) - before
    elapsed, cpu = time.monotonic() - start, time.process_time() - cpu_start
    drops = sum(reader.status().drops for reader in readers)
    not_open = [r.name for r in readers if r.status().state != "open"]
    if not_open:
        print(f"warning: buses not open during the run: {not_open}")
    for reader in readers:
        await reader.stop()
    await asyncio.gather(*consumers)
    return Phase("gateway", frames, elapsed, cpu, drops, {})


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--buses", type=int, default=4)
    parser.add_argument("--source", choices=("blast", "eqgw"), default="blast")
    parser.add_argument(
        "--rate", default="max", help="eqgw source: frames/s generated per bus, or 'max'"
    )
    parser.add_argument("--serve-blast", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--seconds", type=float, default=8.0, help="measured time per phase")
    parser.add_argument("--warmup", type=float, default=1.5)
    parser.add_argument("--queue-size", type=int, default=10000)
    args = parser.parse_args()
    if args.serve_blast:
        return serve_blast()
    logging.basicConfig(level=logging.WARNING)
    # Both phases run python-can's client, which warns on most reads under load; the filter
    # keeps the terminal readable and costs both phases the same.
    install_socketcand_log_filter()

    phases: list[Phase] = []
    server = Server(args.source, args.buses, args.rate)
    phase = measure_bare(server.names, server.port, args.warmup, args.seconds)
    phase.server = server.stop()
    phases.append(phase)

    server = Server(args.source, args.buses, args.rate)
    phase = asyncio.run(
        measure_gateway(server.names, server.port, args.warmup, args.seconds, args.queue_size)
    )
    phase.server = server.stop()
    phases.append(phase)

    bare, gateway = phases
    source = (
        "blast server (receiver-bound)"
        if args.source == "blast"
        else f"eqgw socketcand server generating {args.rate} frames/s per bus"
    )
    print(
        f"socketcand receive, {args.buses} buses from {source}; "
        f"{args.seconds:g} s measured per phase; {os.cpu_count()} CPUs"
    )
    labels = {
        "bare": "python-can bare (SocketCanDaemonBus.recv loop)",
        "gateway": "eqgw BusReader (Notifier -> bounded queue -> async for)",
    }
    for p in phases:
        line = (
            f"  {labels[p.name]:<56} {p.rate:>9,.0f} frames/s   "
            f"cpu {p.cpu_seconds / p.seconds:5.0%}   {p.per_cpu_second:>9,.0f} frames/cpu-s"
        )
        if p.name == "gateway":
            line += f"   reader drops {p.client_drops:,}"
        if args.source == "eqgw":
            line += f"   server drops {p.server.get('totals', {}).get('drops', 0):,}"
        print(line)
    print(
        f"  ratio gateway / bare: {gateway.rate / bare.rate:.2f} in frames/s, "
        f"{gateway.per_cpu_second / bare.per_cpu_second:.2f} in frames per CPU-second"
    )
    print(
        f"  = {gateway.rate / FULL_BUS_FPS:.1f} fully loaded 250 kbit/s buses "
        f"({FULL_BUS_FPS:,} frames/s each) received by one gateway process"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
