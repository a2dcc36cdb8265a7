"""The socketcand server with python-can's socketcand client, in process and across processes."""

from __future__ import annotations

import asyncio
import functools
import json
import os
import signal
import socket
import subprocess
import sys
import tempfile
import time
import xml.etree.ElementTree as ET
from collections.abc import AsyncIterator, Callable, Iterator
from pathlib import Path
from typing import Any, TypeVar

import can
import can.interfaces.virtual
import pytest

from eqgw.bus.config import BusConfig
from eqgw.bus.log_filters import SOCKETCAND_LOGGER, install_socketcand_log_filter
from eqgw.bus.reader import BusReader, ThreadRunner
from eqgw.bus.socketcand_server import (
    GENERATED_ID,
    SocketcandServer,
    format_frame,
    parse_send,
)
from eqgw.bus.writer import BusWriter
from tests.bus_helpers import TIMEOUT, recv_virtual, wait_for, within

REPO = Path(__file__).resolve().parents[2]
T = TypeVar("T")


async def blocking(fn: Callable[[], T]) -> T:
    """Run a blocking python-can call off the loop (the server in this loop must keep going)."""
    runner = ThreadRunner(asyncio.get_running_loop(), "test")
    try:
        return await within(runner.run(fn, what="call"), TIMEOUT)
    finally:
        await runner.join(TIMEOUT)


def seq(msg: can.Message) -> int:
    return int.from_bytes(msg.data[:4], "little")


def frame(i: int, can_id: int = 0x18FEF11E) -> can.Message:
    return can.Message(arbitration_id=can_id, data=i.to_bytes(4, "little") + bytes(4))


def socketcand_config(served: str, port: int, **overrides: object) -> BusConfig:
    values: dict[str, object] = {
        "name": f"{served}/can0",
        "vehicle_id": served,
        "interface": "socketcand",
        "channel": served,
        "options": {"host": "127.0.0.1", "port": port},
    }
    values.update(overrides)
    return BusConfig.model_validate(values)


@pytest.fixture
async def server(channel: str) -> AsyncIterator[SocketcandServer]:
    async with SocketcandServer("127.0.0.1", 0, {"BUS-101": channel}) as srv:
        yield srv


class RawClient:
    """A hand-driven socketcand client, to see the exact bytes on the wire."""

    def __init__(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        self.reader = reader
        self.writer = writer

    @classmethod
    async def connect(cls, port: int, rcvbuf: int | None = None) -> RawClient:
        sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        if rcvbuf is not None:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, rcvbuf)
        sock.setblocking(False)
        await asyncio.get_running_loop().sock_connect(sock, ("127.0.0.1", port))
        reader, writer = await asyncio.open_connection(sock=sock)
        return cls(reader, writer)

    async def command(self, text: str) -> str:
        self.writer.write(text.encode())
        return await self.message()

    async def message(self) -> str:
        data = await within(self.reader.readuntil(b">"), TIMEOUT)
        return data.decode().strip()

    async def close(self) -> None:
        self.writer.close()
        await self.writer.wait_closed()


# -- wire format ------------------------------------------------------------------------------


def test_frame_lines_match_what_socketcand_sends() -> None:
    ext = can.Message(timestamp=1.5, arbitration_id=0x18FEF11E, data=b"\x01\xab")
    std = can.Message(timestamp=2.0, arbitration_id=0x123, is_extended_id=False, data=b"")
    assert format_frame(ext) == "< frame 18FEF11E 1.500000 01AB >"
    assert format_frame(std) == "< frame 123 2.000000  >"
    assert format_frame(can.Message(arbitration_id=1, is_remote_frame=True)) is None
    # python-can's own parser reads both back, the empty payload included.
    from can.interfaces.socketcand.socketcand import convert_ascii_message_to_can_message

    for msg, line in ((ext, format_frame(ext)), (std, format_frame(std))):
        assert line is not None
        parsed = convert_ascii_message_to_can_message(line)
        assert parsed.arbitration_id == msg.arbitration_id
        assert parsed.is_extended_id == msg.is_extended_id
        assert parsed.data == msg.data
        assert parsed.timestamp == msg.timestamp


def test_send_commands_parse_like_socketcand() -> None:
    from can.interfaces.socketcand.socketcand import convert_can_message_to_ascii_message

    original = can.Message(arbitration_id=0x18EA1ED8, data=b"\x00\xfe\xca")
    line = convert_can_message_to_ascii_message(original)
    parsed = parse_send(line.strip("<> ").split()[1:])
    assert parsed.arbitration_id == 0x18EA1ED8 and parsed.is_extended_id
    assert parsed.data == original.data
    std = parse_send(["7FF", "0"])
    assert std.arbitration_id == 0x7FF and not std.is_extended_id and std.data == b""
    for bad in (["123"], ["123", "2", "1"], ["123", "9", *["0"] * 9], ["800", "0"], ["xyz", "0"]):
        with pytest.raises(ValueError):
            parse_send(bad)


# -- in process -------------------------------------------------------------------------------


async def test_protocol_handshake_echo_and_errors(server: SocketcandServer) -> None:
    client = await RawClient.connect(server.port)
    try:
        assert await client.message() == "< hi >"
        assert await client.command("< echo >") == "< echo >"
        assert (await client.command("< send 123 1 0 >")).startswith("< error ")
        assert (await client.command("< rawmode >")).startswith("< error ")
        assert await client.command("< open NOPE >") == "< error unknown bus NOPE >"
        assert (await client.command("< bcmmode >")).startswith("< error unsupported")
        assert await client.command("< open BUS-101 >") == "< ok >"
        assert (await client.command("< open BUS-101 >")).startswith("< error ")
        assert await client.command("< rawmode >") == "< ok >"
        assert (await client.command("< send 123 2 1 >")).startswith("< error bad send")
        assert await client.command("< echo >") == "< echo >"
        assert server.served() == ["BUS-101"]
        assert [c.bus for c in server.clients()] == ["BUS-101"]
    finally:
        await client.close()
    await wait_for(lambda: not server.clients(), "the server to drop the client")


async def test_python_can_client_receives_and_sends_through_the_server(
    server: SocketcandServer, sim: can.BusABC
) -> None:
    client = await blocking(
        functools.partial(
            can.Bus, interface="socketcand", channel="BUS-101", host="127.0.0.1", port=server.port
        )
    )
    try:
        for i in range(20):
            sim.send(frame(i))
        sim.send(can.Message(arbitration_id=0x1A, is_extended_id=False, data=b"\x42"))
        got = [await blocking(functools.partial(client.recv, TIMEOUT)) for _ in range(21)]
        assert all(m is not None for m in got)
        assert [seq(m) for m in got[:20] if m] == list(range(20))
        assert got[20] is not None and not got[20].is_extended_id
        assert got[20].arbitration_id == 0x1A and got[20].data == b"\x42"
        # The bus timestamp crosses the wire (to the microsecond the protocol carries).
        assert got[0] is not None and got[0].timestamp > 1e9
        await blocking(functools.partial(client.send, frame(77, 0x18EA1ED8)))
        sent = await recv_virtual(sim)
        assert sent.arbitration_id == 0x18EA1ED8 and seq(sent) == 77
    finally:
        await blocking(client.shutdown)
    await wait_for(lambda: not server.clients(), "the server to drop the client")


async def test_a_clients_frames_reach_the_other_clients_but_not_itself(
    server: SocketcandServer, sim: can.BusABC
) -> None:
    port = server.port
    async with (
        BusReader(socketcand_config("BUS-101", port)) as gateway,
        BusReader(socketcand_config("BUS-101", port, name="tool")) as tool,
    ):
        await gateway.wait_open(TIMEOUT)
        await tool.wait_open(TIMEOUT)
        await BusWriter(gateway).send(0x18EA1ED8, b"\x01\x02\x03")
        at_tool = await within(tool.get(), TIMEOUT)
        at_sim = await recv_virtual(sim)
        for msg in (at_tool, at_sim):
            assert msg.arbitration_id == 0x18EA1ED8 and msg.data == b"\x01\x02\x03"
        sim.send(frame(5))
        assert seq(await within(tool.get(), TIMEOUT)) == 5
        # The gateway's first frame is the simulator's, not its own echo.
        assert seq(await within(gateway.get(), TIMEOUT)) == 5


async def test_unknown_bus_name_is_reported_by_the_reader(server: SocketcandServer) -> None:
    reader = BusReader(socketcand_config("NO-SUCH-BUS", server.port), backoff=(0.05, 0.2))
    async with reader:
        await wait_for(lambda: reader.status().last_error is not None, "an open failure")
        error = reader.status().last_error
        assert error is not None and "unknown bus NO-SUCH-BUS" in error
        assert reader.status().state != "open"


async def test_unreachable_server_is_reported_quickly() -> None:
    with socket.socket() as placeholder:
        placeholder.bind(("127.0.0.1", 0))
        port = placeholder.getsockname()[1]
    reader = BusReader(socketcand_config("BUS-101", port), backoff=(0.05, 0.2))
    async with reader:
        await wait_for(lambda: reader.status().last_error is not None, "an open failure")
        error = reader.status().last_error
        assert error is not None and "unreachable" in error and "refused" in error


async def test_slow_client_drops_and_is_disconnected_without_slowing_the_others(
    channel: str, sim: can.BusABC, caplog: pytest.LogCaptureFixture
) -> None:
    # 2 s, not less: under a loaded CI run the reading client itself can be held up for the
    # better part of a second (GIL, collector), and a shorter timeout then disconnects it too,
    # losing the frames of its reconnect.
    server = SocketcandServer(
        "127.0.0.1", 0, {"BUS-101": channel}, client_queue_size=2000, stall_timeout=2.0
    )
    async with server:
        # A plain socket that does the handshake and then never reads again; a small receive
        # buffer so the server's writes back up after a few kilobytes.
        stalled = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        stalled.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
        stalled.setblocking(False)
        loop = asyncio.get_running_loop()
        try:
            await loop.sock_connect(stalled, ("127.0.0.1", server.port))
            for command in (b"< open BUS-101 >", b"< rawmode >"):
                await within(loop.sock_recv(stalled, 64), TIMEOUT)
                await loop.sock_sendall(stalled, command)
            stalled_peer = f"127.0.0.1:{stalled.getsockname()[1]}"
            await wait_for(lambda: any(c.rawmode for c in server.clients()), "rawmode")
            async with BusReader(socketcand_config("BUS-101", server.port)) as reader:
                await reader.wait_open(TIMEOUT)
                stalled_drops = 0

                def stalled_present() -> bool:
                    nonlocal stalled_drops
                    mine = [c for c in server.clients() if c.peer == stalled_peer]
                    if mine:
                        stalled_drops = mine[0].drops
                    return bool(mine)

                sent = 0
                received: list[can.Message] = []
                while stalled_present() and sent < 500_000:
                    for _ in range(200):
                        sim.send(frame(sent))
                        sent += 1
                    # The reading client keeps up: the stalled one does not hold it back.
                    while len(received) < sent:
                        received.extend(await within(reader.get_batch(), TIMEOUT))
                assert not stalled_present(), "the stalled client was never disconnected"
                assert stalled_drops > 0
                assert [seq(m) for m in received] == list(range(sent))
                assert reader.status().drops == 0
                assert [c.drops for c in server.clients()] == [0]
        finally:
            stalled.close()
    assert any("disconnecting" in r.getMessage() for r in caplog.records)


async def test_split_frame_warnings_are_summarised(
    server: SocketcandServer, sim: can.BusABC, caplog: pytest.LogCaptureFixture
) -> None:
    summary = install_socketcand_log_filter()
    before = summary.counts()["Got incomplete message => waiting for more data"]
    async with BusReader(socketcand_config("BUS-101", server.port)) as reader:
        await reader.wait_open(TIMEOUT)
        for i in range(3000):
            sim.send(frame(i))
        received = 0
        while received < 3000:
            received += len(await within(reader.get_batch(), TIMEOUT))
    after = summary.counts()["Got incomplete message => waiting for more data"]
    # 3000 lines of 46 bytes read 1024 bytes at a time cannot all end on a frame boundary.
    assert after > before
    shown = [
        r
        for r in caplog.records
        if r.name == SOCKETCAND_LOGGER and r.getMessage().startswith("Got incomplete")
    ]
    assert len(shown) <= 1


async def test_udp_beacon_advertises_the_served_buses(channel: str) -> None:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as listener:
        listener.bind(("127.0.0.1", 0))
        listener.setblocking(False)
        server = SocketcandServer(
            "127.0.0.1",
            0,
            {"BUS-101": channel, "BUS-102": channel},
            beacon_interval=0.05,
            beacon_address=listener.getsockname(),
        )
        async with server:
            data = await within(asyncio.get_running_loop().sock_recv(listener, 4096), TIMEOUT)
    root = ET.fromstring(data)
    assert root.tag == "CANBeacon"
    assert [b.attrib["name"] for b in root.iter("Bus")] == ["BUS-101", "BUS-102"]
    url = root.find("URL")
    assert url is not None and url.text is not None
    assert url.text.startswith("can://127.0.0.1:")


# -- across processes -------------------------------------------------------------------------


class ServerProcess:
    """`python -m eqgw.bus.socketcand_server` in a subprocess."""

    def __init__(self, port: int, *args: str) -> None:
        self.log = tempfile.TemporaryFile()
        self.proc = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "eqgw.bus.socketcand_server",
                "--listen",
                f"127.0.0.1:{port}",
                *args,
            ],
            cwd=REPO,
            stdout=subprocess.PIPE,
            stderr=self.log,
        )
        assert self.proc.stdout is not None
        os.set_blocking(self.proc.stdout.fileno(), False)
        self.port = port

    async def ready(self) -> int:
        """Wait for the server's `listening HOST:PORT ...` line; returns the port."""
        assert self.proc.stdout is not None
        line = b""
        deadline = time.monotonic() + 60  # a Python process starting on busy shared cores
        while not line.endswith(b"\n"):
            chunk = self.proc.stdout.read()
            if chunk:
                line += chunk
            elif self.proc.poll() is not None or time.monotonic() > deadline:
                self.log.seek(0)
                pytest.fail(f"server did not start: {self.log.read().decode()}")
            else:
                await asyncio.sleep(0.02)
        self.port = int(line.split()[1].decode().rsplit(":", 1)[1])
        return self.port

    def kill(self) -> None:
        self.proc.kill()
        self.proc.wait()
        self.close()

    def close(self) -> None:
        if self.proc.stdout is not None:
            self.proc.stdout.close()
        self.log.close()

    async def terminate(self) -> dict[str, Any]:
        self.proc.send_signal(signal.SIGTERM)
        deadline = time.monotonic() + TIMEOUT
        while self.proc.poll() is None:
            if time.monotonic() > deadline:
                self.proc.kill()
            await asyncio.sleep(0.02)
        assert self.proc.stdout is not None
        os.set_blocking(self.proc.stdout.fileno(), True)
        out = self.proc.stdout.read().decode().strip().splitlines()
        self.close()
        return dict(json.loads(out[-1])) if out else {}


@pytest.fixture
def processes() -> Iterator[list[ServerProcess]]:
    started: list[ServerProcess] = []
    yield started
    for proc in started:
        if proc.proc.poll() is None:
            proc.kill()


async def test_reader_survives_the_server_process_being_killed_and_restarted(
    processes: list[ServerProcess],
) -> None:
    generate = ("--bus", "BUS-101=vc-101", "--generate", "BUS-101:1000")
    first = ServerProcess(0, *generate)
    processes.append(first)
    port = await first.ready()
    reader = BusReader(socketcand_config("BUS-101", port), backoff=(0.1, 0.5))
    async with reader:
        await reader.wait_open(TIMEOUT)
        frames: list[can.Message] = []
        while len(frames) < 300:
            frames.extend(await within(reader.get_batch(), TIMEOUT))
        assert all(m.arbitration_id == GENERATED_ID and m.is_extended_id for m in frames)
        assert all(m.channel == "BUS-101/can0" for m in frames)
        numbers = [seq(m) for m in frames]
        assert numbers == list(range(numbers[0], numbers[0] + len(numbers)))

        first.kill()
        states: list[str] = []

        def record(target: str) -> Callable[[], bool]:
            def check() -> bool:
                state = reader.status().state
                if not states or states[-1] != state:
                    states.append(state)
                return state == target

            return check

        await wait_for(record("backoff"), "the reader to notice the dead server")
        error = reader.status().last_error
        assert error is not None and "closed the connection" in error
        # Whatever was still in flight is drained; then the bus is silent.
        while reader.status().queued:
            await reader.get_batch()

        restarted_at = time.time()
        second = ServerProcess(port, *generate)
        processes.append(second)
        await second.ready()
        await wait_for(record("open"), "the reader to reconnect")
        assert states[0] in ("open", "backoff") and states[-1] == "open" and "backoff" in states
        status = reader.status()
        assert status.reconnects == 1
        assert status.drops == 0
        after: list[can.Message] = []
        while len(after) < 300:
            after.extend(await within(reader.get_batch(), TIMEOUT))
        # Stamped by the second process (same host clock) and gap-free from where we joined.
        assert all(m.timestamp >= restarted_at for m in after)
        renumbered = [seq(m) for m in after]
        assert renumbered == list(range(renumbered[0], renumbered[0] + len(renumbered)))
        summary = await second.terminate()
    assert summary["generated"]["vc-101"] > 0
    assert reader.status().state == "closed"


async def test_frames_from_the_gateway_reach_the_other_process(
    processes: list[ServerProcess],
) -> None:
    server = ServerProcess(0, "--bus", "BUS-101=vc-101", "--bus", "BUS-102=vc-102")
    processes.append(server)
    port = await server.ready()
    async with (
        BusReader(socketcand_config("BUS-101", port)) as gateway,
        BusReader(socketcand_config("BUS-101", port, name="tool")) as tool,
        BusReader(socketcand_config("BUS-102", port)) as other_bus,
    ):
        for reader in (gateway, tool, other_bus):
            await reader.wait_open(TIMEOUT)
        await BusWriter(gateway).send(0x18EA1ED8, b"\xca\xfe\x00")
        msg = await within(tool.get(), TIMEOUT)
        assert msg.arbitration_id == 0x18EA1ED8 and msg.data == b"\xca\xfe\x00"
        assert other_bus.status().frames_total == 0
    await server.terminate()


def test_server_command_line_rejects_nonsense() -> None:
    result = subprocess.run(
        [sys.executable, "-m", "eqgw.bus.socketcand_server", "--generate", "BUS:fast"],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=TIMEOUT,
    )
    assert result.returncode == 2
    assert "RATE" in result.stderr
