"""A socketcand server (raw mode) that lets other processes open python-can virtual channels.

Each client connection gets its own virtual bus endpoint on the channel it opens, so frames
flow both ways between the simulator's endpoint and every client, and one client's frames
reach the others, as on a real bus. The wire format follows what python-can's `socketcand`
client speaks: `< hi >`, `< open NAME >` / `< ok >`, `< rawmode >` / `< ok >`, then
`< frame ID SECS.USECS DATAHEX >` to the client and `< send ID DLC B0 B1 ... >` from it.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import dataclasses
import functools
import json
import logging
import signal
import socket
import struct
import sys
import threading
import time
from collections.abc import Sequence
from typing import Any
from xml.sax.saxutils import quoteattr

import can

from eqgw.bus.errors import SocketcandServerError
from eqgw.bus.reader import FrameHandoff, HandoffListener, ThreadRunner
from eqgw.describe import describe
from eqgw.tasks import cancel_and_wait

log = logging.getLogger(__name__)

# Longest command a client may send before we call it garbage.
MAX_COMMAND_BYTES = 4096
# Frames written to a client per drain; about 45 bytes each, so close to one socket buffer.
FORWARD_BATCH = 1024
DEFAULT_BEACON_PORT = 42000


def format_frame(msg: can.Message) -> str | None:
    """The socketcand raw-mode line for a frame, or None for one the protocol cannot carry."""
    if msg.is_error_frame:
        return f"< error {msg.arbitration_id & 0x1FFFFFFF:08X} {msg.timestamp:.6f} >"
    if msg.is_remote_frame:
        return None
    can_id = (
        f"{msg.arbitration_id & 0x1FFFFFFF:08X}"
        if msg.is_extended_id
        else f"{msg.arbitration_id & 0x7FF:03X}"
    )
    # An empty payload still gets its field separator: python-can's parser needs three fields.
    return f"< frame {can_id} {msg.timestamp:.6f} {msg.data.hex().upper()} >"


def parse_send(args: Sequence[str]) -> can.Message:
    """The frame of a `< send ID DLC B0 ... >` command (args without the verb)."""
    if len(args) < 2:
        raise ValueError("send needs ID DLC [bytes]")
    id_text, dlc_text, *byte_texts = args
    can_id = int(id_text, 16)
    # socketcand tells the formats apart by width: 3 hex digits standard, 8 extended.
    extended = len(id_text) > 3
    if not 0 <= can_id <= (0x1FFFFFFF if extended else 0x7FF):
        raise ValueError(f"identifier {id_text} out of range")
    dlc = int(dlc_text, 16)
    if not 0 <= dlc <= 8:
        raise ValueError(f"dlc {dlc_text} is not 0..8")
    if len(byte_texts) != dlc:
        raise ValueError(f"dlc {dlc} but {len(byte_texts)} data bytes")
    data = bytes(int(b, 16) for b in byte_texts)
    return can.Message(arbitration_id=can_id, is_extended_id=extended, data=data, is_rx=False)


@dataclasses.dataclass(frozen=True, slots=True)
class ClientStatus:
    """One connected client, for logs and tests."""

    peer: str
    bus: str | None
    rawmode: bool
    connected_at: float
    frames_sent: int
    frames_received: int
    drops: int


class _Session:
    """One client connection: command parsing, its virtual endpoint and its frame forwarder."""

    def __init__(
        self,
        server: SocketcandServer,
        reader: asyncio.StreamReader,
        writer: asyncio.StreamWriter,
    ) -> None:
        self.server = server
        self.reader = reader
        self.writer = writer
        peer = writer.get_extra_info("peername")
        self.peer = f"{peer[0]}:{peer[1]}" if isinstance(peer, tuple) else str(peer)
        self.connected_at = time.time()
        self.bus_name: str | None = None
        self.endpoint: can.BusABC | None = None
        self.notifier: can.Notifier | None = None
        self.handoff: FrameHandoff | None = None
        self.forwarder: asyncio.Task[None] | None = None
        self.frames_sent = 0
        self.frames_received = 0
        self.unsupported = 0
        self._drops_reported = 0
        self._drops_reported_at = 0.0

    def status(self) -> ClientStatus:
        return ClientStatus(
            peer=self.peer,
            bus=self.bus_name,
            rawmode=self.forwarder is not None,
            connected_at=self.connected_at,
            frames_sent=self.frames_sent,
            frames_received=self.frames_received,
            drops=self.handoff.drops if self.handoff else 0,
        )

    async def run(self) -> None:
        log.debug("client %s connected", self.peer)
        try:
            self.writer.write(b"< hi >")
            await self.writer.drain()
            await self._read_commands()
        except (ConnectionError, asyncio.IncompleteReadError) as exc:
            log.debug("client %s: %s", self.peer, describe(exc))
        finally:
            await self.close()
            log.debug("client %s gone", self.peer)

    async def _read_commands(self) -> None:
        buf = b""
        while True:
            data = await self.reader.read(65536)
            if not data:
                return
            buf += data
            while True:
                start = buf.find(b"<")
                if start < 0:
                    buf = b""
                    break
                end = buf.find(b">", start)
                if end < 0:
                    buf = buf[start:]
                    if len(buf) > MAX_COMMAND_BYTES:
                        log.warning("client %s: unterminated command, disconnecting", self.peer)
                        return
                    break
                command = buf[start + 1 : end].decode("ascii", "replace").split()
                buf = buf[end + 1 :]
                self._handle(command)
            await self.writer.drain()

    def _reply(self, text: str) -> None:
        self.writer.write(text.encode("ascii", "replace"))

    def _error(self, reason: str) -> None:
        # '<' and '>' would end the message early on the client's side.
        safe = reason.replace("<", "(").replace(">", ")")
        self._reply(f"< error {safe} >")

    def _handle(self, command: list[str]) -> None:
        if not command:
            self._error("empty command")
            return
        verb, args = command[0], command[1:]
        if verb == "echo":
            self._reply("< echo >")
        elif verb == "open":
            self._open(args)
        elif verb == "rawmode":
            self._rawmode()
        elif verb == "send":
            self._send(args)
        else:
            self._error(f"unsupported command {verb}")

    def _open(self, args: list[str]) -> None:
        if self.endpoint is not None:
            self._error(f"bus {self.bus_name} already open")
            return
        if len(args) != 1:
            self._error("open needs one bus name")
            return
        name = args[0]
        channel = self.server.channel_of(name)
        if channel is None:
            self._error(f"unknown bus {name}")
            return
        loop = asyncio.get_running_loop()
        self.endpoint = can.Bus(interface="virtual", channel=channel)
        self.handoff = FrameHandoff(loop, self.server.client_queue_size)
        listener = HandoffListener(self.handoff, loop, self._on_receive_error)
        # Read the endpoint from its first moment: python-can's virtual queues are unbounded,
        # so an unread endpoint would grow; frames before rawmode are discarded there.
        self.notifier = can.Notifier(self.endpoint, [listener], timeout=0.2)
        self.bus_name = name
        self._reply("< ok >")

    def _on_receive_error(self, exc: Exception) -> None:
        log.warning("client %s: virtual endpoint failed: %s", self.peer, describe(exc))
        self.writer.transport.abort()

    def _rawmode(self) -> None:
        if self.handoff is None:
            self._error("rawmode needs an open bus")
            return
        if self.forwarder is not None:
            self._reply("< ok >")
            return
        # Frames from before rawmode were never asked for.
        self.handoff.clear()
        self._reply("< ok >")
        self.forwarder = asyncio.create_task(
            self._forward(self.handoff), name=f"socketcand {self.peer}: forward"
        )

    def _send(self, args: list[str]) -> None:
        if self.endpoint is None:
            self._error("send needs an open bus")
            return
        try:
            msg = parse_send(args)
        except ValueError as exc:
            self._error(f"bad send: {exc}")
            return
        try:
            # Virtual queues are unbounded: this never blocks the loop.
            self.endpoint.send(msg)
        except can.CanError as exc:
            self._error(f"send failed: {describe(exc)}")
            return
        self.frames_received += 1

    async def _forward(self, handoff: FrameHandoff) -> None:
        # python-can's client reads the `< ok >` of rawmode with one recv() and compares it
        # whole; a frame arriving in the same read would fail its handshake. Frames of the
        # grace period wait in the handoff.
        await asyncio.sleep(self.server.rawmode_grace)
        try:
            while True:
                batch = await handoff.get_batch(FORWARD_BATCH)
                if not batch:
                    return
                lines = [line for msg in batch if (line := format_frame(msg)) is not None]
                self.unsupported += len(batch) - len(lines)
                self.writer.write("".join(lines).encode("ascii"))
                self.frames_sent += len(lines)
                self._report_drops(handoff)
                try:
                    async with asyncio.timeout(self.server.stall_timeout):
                        await self.writer.drain()
                except TimeoutError:
                    log.warning(
                        "client %s on %s read nothing for %.0f s, disconnecting it",
                        self.peer,
                        self.bus_name,
                        self.server.stall_timeout,
                    )
                    self.writer.transport.abort()
                    return
        except ConnectionError as exc:
            log.debug("client %s: %s", self.peer, describe(exc))
            self.writer.transport.abort()

    def _report_drops(self, handoff: FrameHandoff) -> None:
        now = time.monotonic()
        if handoff.drops > self._drops_reported and now - self._drops_reported_at >= 10.0:
            log.warning(
                "client %s on %s reads too slowly: %d frames dropped so far",
                self.peer,
                self.bus_name,
                handoff.drops,
            )
            self._drops_reported = handoff.drops
            self._drops_reported_at = now

    async def close(self) -> None:
        if self.forwarder is not None:
            await cancel_and_wait(self.forwarder)
        if self.handoff is not None:
            self.handoff.close()
        endpoint, notifier = self.endpoint, self.notifier
        self.endpoint = self.notifier = None
        if endpoint is not None:
            # Stopping a Notifier joins its thread: not on the event loop. The endpoint itself
            # is shut down on the loop: python-can's virtual send() walks the channel's list of
            # queues without its lock, and a queue removed from another thread mid-walk makes
            # it skip the next one, a frame lost for another client. Senders on this loop (the
            # simulator, the tests) never see the list change under them.
            await self.server.threads.run(
                functools.partial(_stop_notifier, notifier), what="stop endpoint reader"
            )
            endpoint.shutdown()
        self.writer.close()
        with contextlib.suppress(ConnectionError):
            await self.writer.wait_closed()


def _stop_notifier(notifier: can.Notifier | None) -> None:
    if notifier is not None:
        notifier.stop(timeout=2.0)


class SocketcandServer:
    """Serves python-can virtual channels over TCP with the socketcand protocol (raw mode)."""

    def __init__(
        self,
        host: str,
        port: int,
        buses: dict[str, str],
        *,
        client_queue_size: int = 10000,
        rawmode_grace: float = 0.1,
        stall_timeout: float = 30.0,
        beacon_interval: float | None = None,
        beacon_address: tuple[str, int] = ("255.255.255.255", DEFAULT_BEACON_PORT),
    ) -> None:
        for name in buses:
            _check_bus_name(name)
        self.host = host
        self.requested_port = port
        self.client_queue_size = client_queue_size
        self.rawmode_grace = rawmode_grace
        self.stall_timeout = stall_timeout
        self.beacon_interval = beacon_interval
        self.beacon_address = beacon_address
        self._buses = dict(buses)
        self._server: asyncio.Server | None = None
        self._sessions: dict[_Session, asyncio.Task[None]] = {}
        self._beacon: asyncio.Task[None] | None = None
        self._threads: ThreadRunner | None = None
        # Counters of clients that have left, so totals() covers the server's whole life.
        self._departed = {"clients": 0, "frames_sent": 0, "frames_received": 0, "drops": 0}

    @property
    def port(self) -> int:
        """The port actually listened on (the OS's choice when 0 was asked for)."""
        if self._server is None or not self._server.sockets:
            raise SocketcandServerError("server is not started")
        return int(self._server.sockets[0].getsockname()[1])

    @property
    def threads(self) -> ThreadRunner:
        """Runner for the blocking calls of client sessions."""
        if self._threads is None:
            raise SocketcandServerError("server is not started")
        return self._threads

    def served(self) -> list[str]:
        """Names clients can open."""
        return sorted(self._buses)

    def channel_of(self, name: str) -> str | None:
        """The virtual channel behind a served name."""
        return self._buses.get(name)

    def add_bus(self, name: str, channel: str) -> None:
        """Serve another virtual channel (e.g. a vehicle added to a running simulation)."""
        _check_bus_name(name)
        self._buses[name] = channel

    def remove_bus(self, name: str) -> None:
        """Stop serving a name and disconnect its clients."""
        self._buses.pop(name, None)
        for session in list(self._sessions):
            if session.bus_name == name:
                session.writer.transport.abort()

    def clients(self) -> list[ClientStatus]:
        """Every connected client."""
        return [session.status() for session in self._sessions]

    def totals(self) -> dict[str, int]:
        """Clients served and frames sent, received and dropped since start, departed included."""
        totals = dict(self._departed)
        for client in self.clients():
            totals["clients"] += 1
            totals["frames_sent"] += client.frames_sent
            totals["frames_received"] += client.frames_received
            totals["drops"] += client.drops
        return totals

    async def start(self) -> None:
        """Listen; raises SocketcandServerError when the address is unusable."""
        if self._server is not None:
            raise SocketcandServerError("server already started")
        self._threads = ThreadRunner(asyncio.get_running_loop(), "socketcand server")
        try:
            self._server = await asyncio.start_server(
                self._accept, self.host, self.requested_port, reuse_address=True
            )
        except OSError as exc:
            raise SocketcandServerError(
                f"cannot listen on {self.host}:{self.requested_port}: {describe(exc)}"
            ) from exc
        log.info(
            "socketcand server on %s:%d serving %s", self.host, self.port, ", ".join(self.served())
        )
        if self.beacon_interval:
            self._beacon = asyncio.create_task(self._send_beacons(), name="socketcand beacon")

    async def stop(self) -> None:
        """Stop listening, disconnect every client and release their endpoints."""
        server, self._server = self._server, None
        if server is None:
            return
        server.close()
        if self._beacon is not None:
            await cancel_and_wait(self._beacon)
        for session in list(self._sessions):
            session.writer.transport.abort()
        await asyncio.gather(*self._sessions.values(), return_exceptions=True)
        await server.wait_closed()
        if self._threads is not None and not await self._threads.join(10.0):
            log.warning("socketcand server: a client endpoint did not close within 10 s")

    async def __aenter__(self) -> SocketcandServer:
        await self.start()
        return self

    async def __aexit__(self, *exc_info: object) -> None:
        await self.stop()

    async def _accept(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        session = _Session(self, reader, writer)
        task = asyncio.current_task()
        assert task is not None
        self._sessions[session] = task
        try:
            await session.run()
        finally:
            del self._sessions[session]
            status = session.status()
            self._departed["clients"] += 1
            self._departed["frames_sent"] += status.frames_sent
            self._departed["frames_received"] += status.frames_received
            self._departed["drops"] += status.drops

    def beacon_payload(self) -> bytes:
        """The UDP discovery beacon socketcand clients (python-can's detect_beacon) listen for."""
        host = self.host
        if host in ("", "0.0.0.0"):
            host = socket.gethostbyname(socket.gethostname())
        buses = "".join(f"<Bus name={quoteattr(name)}/>" for name in self.served())
        return (
            '<CANBeacon name="eqgw" type="SocketCAN" description="eqgw socketcand server">'
            f"<URL>can://{host}:{self.port}</URL>{buses}</CANBeacon>"
        ).encode()

    async def _send_beacons(self) -> None:
        assert self.beacon_interval is not None
        loop = asyncio.get_running_loop()
        transport, _ = await loop.create_datagram_endpoint(
            asyncio.DatagramProtocol, family=socket.AF_INET, allow_broadcast=True
        )
        try:
            while True:
                transport.sendto(self.beacon_payload(), self.beacon_address)
                await asyncio.sleep(self.beacon_interval)
        finally:
            transport.close()


def _check_bus_name(name: str) -> None:
    if not name or any(c.isspace() or c in "<>" for c in name):
        raise SocketcandServerError(f"bus name {name!r} cannot travel in a socketcand command")


# -- the runnable entry point: serve virtual channels, optionally with synthetic traffic -------

GENERATED_ID = 0x18FF001E


class FrameGenerator(threading.Thread):
    """Sends synthetic 29-bit frames (a sequence number in bytes 0-3) on a virtual channel."""

    def __init__(self, channel: str, rate: float | None) -> None:
        super().__init__(name=f"generate {channel}", daemon=True)
        self.channel = channel
        self.rate = rate
        self.sent = 0
        self.skipped = 0
        self._stop_event = threading.Event()

    def stop(self) -> None:
        """Ask the thread to end."""
        self._stop_event.set()

    def run(self) -> None:
        """Send until stopped, at `rate` frames/s or as fast as possible when rate is None."""
        bus = can.Bus(interface="virtual", channel=self.channel)
        try:
            start = time.monotonic()
            while not self._stop_event.is_set():
                if self.rate is None:
                    burst = 500
                else:
                    due = int((time.monotonic() - start) * self.rate)
                    if due - self.sent - self.skipped > self.rate:
                        # More than a second behind: skip rather than burst to catch up.
                        self.skipped = due - self.sent
                    burst = min(due - self.sent - self.skipped, 500)
                for _ in range(burst):
                    data = struct.pack("<I", self.sent & 0xFFFFFFFF) + b"\xff\xff\xff\xff"
                    bus.send(can.Message(arbitration_id=GENERATED_ID, data=data))
                    self.sent += 1
                # Frames clients send reach this endpoint too; unread they would pile up.
                while bus.recv(0) is not None:
                    pass
                time.sleep(0.002 if burst < 500 else 0)
        finally:
            bus.shutdown()


def _parse_listen(text: str) -> tuple[str, int]:
    host, sep, port = text.rpartition(":")
    if not sep or not port.isdigit():
        raise argparse.ArgumentTypeError(f"expected HOST:PORT, got {text!r}")
    return host or "127.0.0.1", int(port)


def _parse_bus(text: str) -> tuple[str, str]:
    name, sep, channel = text.partition("=")
    if not name or (sep and not channel):
        raise argparse.ArgumentTypeError(f"expected NAME[=VIRTUAL_CHANNEL], got {text!r}")
    return name, channel or name


def _parse_generate(text: str) -> tuple[str, float | None]:
    name, sep, rate = text.rpartition(":")
    if not sep or not name:
        raise argparse.ArgumentTypeError(f"expected NAME:RATE, got {text!r}")
    if rate == "max":
        return name, None
    try:
        value = float(rate)
    except ValueError:
        raise argparse.ArgumentTypeError(f"RATE is frames/s or 'max', got {rate!r}") from None
    if value <= 0:
        raise argparse.ArgumentTypeError("RATE must be positive")
    return name, value


def build_parser() -> argparse.ArgumentParser:
    """Command line of `python -m eqgw.bus.socketcand_server`."""
    parser = argparse.ArgumentParser(
        prog="python -m eqgw.bus.socketcand_server",
        description="Serve python-can virtual channels over the socketcand protocol.",
    )
    parser.add_argument("--listen", type=_parse_listen, default=("127.0.0.1", 29536))
    parser.add_argument(
        "--bus",
        type=_parse_bus,
        action="append",
        default=[],
        metavar="NAME=CHANNEL",
        help="serve virtual CHANNEL as NAME (repeatable; CHANNEL defaults to NAME)",
    )
    parser.add_argument(
        "--generate",
        type=_parse_generate,
        action="append",
        default=[],
        metavar="NAME:RATE",
        help="send synthetic frames on served bus NAME at RATE frames/s ('max': unpaced)",
    )
    parser.add_argument("--beacon", type=float, default=None, metavar="SECONDS")
    parser.add_argument("--log-level", default="INFO")
    return parser


async def serve(args: argparse.Namespace) -> dict[str, Any]:
    """Run the server until SIGINT/SIGTERM; returns final counters."""
    buses = dict(args.bus)
    for name, _rate in args.generate:
        buses.setdefault(name, name)
    if not buses:
        raise SocketcandServerError("nothing to serve: give --bus NAME=CHANNEL")
    host, port = args.listen
    server = SocketcandServer(host, port, buses, beacon_interval=args.beacon)
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, stop.set)
    generators = [FrameGenerator(buses[name], rate) for name, rate in args.generate]
    async with server:
        for generator in generators:
            generator.start()
        # The parent process (tests, the benchmark) waits for this line to learn the port.
        print(f"listening {host}:{server.port} {' '.join(server.served())}", flush=True)  # noqa: T201
        await stop.wait()
        for generator in generators:
            generator.stop()
        for generator in generators:
            await asyncio.to_thread(generator.join)
        clients = [dataclasses.asdict(c) for c in server.clients()]
    return {
        "generated": {g.channel: g.sent for g in generators},
        "skipped": {g.channel: g.skipped for g in generators},
        "clients": clients,
        "totals": server.totals(),
    }


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of `python -m eqgw.bus.socketcand_server`."""
    args = build_parser().parse_args(argv)
    logging.basicConfig(
        level=args.log_level.upper(), format="%(asctime)s %(levelname)s %(name)s: %(message)s"
    )
    try:
        summary = asyncio.run(serve(args))
    except SocketcandServerError as exc:
        log.error("%s", exc)
        return 1
    print(json.dumps(summary), flush=True)  # noqa: T201
    return 0


if __name__ == "__main__":
    sys.exit(main())
