"""One live CAN bus as an asyncio frame source: open it, read it, reopen it, report on it.

Frames cross from python-can's reader thread into asyncio through `FrameHandoff`, a bounded
buffer. `can.Notifier(..., loop=loop)` would schedule one event-loop callback per frame with
no bound: a stalled loop grows memory without limit and every frame pays a self-pipe wake-up.
So the Notifier runs without a loop, its thread appends to the bounded buffer (dropping and
counting when full) and wakes the loop only when a consumer is waiting.
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
import dataclasses
import functools
import logging
import socket
import threading
import time
import weakref
from collections.abc import AsyncIterator, Callable
from typing import Any, Literal, TypeVar

import can
from can.interfaces.socketcand import SocketCanDaemonBus

from eqgw.bus.config import BusConfig
from eqgw.bus.errors import (
    BusClosedError,
    BusNotOpenError,
    BusOpenError,
    BusSendError,
    BusStalledError,
)
from eqgw.bus.log_filters import install_socketcand_log_filter
from eqgw.describe import describe
from eqgw.protocol.address_claim import CLAIM_WAIT_S, AddressClaimer
from eqgw.protocol.responder import GatewayResponder
from eqgw.tasks import backoff_delay, cancel_and_wait

log = logging.getLogger(__name__)

BusState = Literal["connecting", "open", "backoff", "closed"]
T = TypeVar("T")

# How long python-can's reader thread blocks in recv(); bounds how long stopping a bus takes.
NOTIFIER_POLL_S = 0.2


def _call_in_loop(loop: asyncio.AbstractEventLoop, fn: Callable[..., object], *args: Any) -> None:
    """Schedule fn on the loop from another thread, ignoring a loop that is already closed."""
    try:
        loop.call_soon_threadsafe(fn, *args)
    except RuntimeError:
        # The loop closed under a thread that outlived it; nobody is left to tell.
        pass


class FrameHandoff:
    """Bounded buffer carrying frames from a python-can reader thread to asyncio consumers."""

    def __init__(
        self, loop: asyncio.AbstractEventLoop, maxsize: int, *, channel: str | None = None
    ) -> None:
        if maxsize < 1:
            raise ValueError("maxsize must be at least 1")
        self.maxsize = maxsize
        self.channel = channel
        self.frames_total = 0
        self.drops = 0
        self._loop = loop
        self._buf: collections.deque[can.Message] = collections.deque()
        self._lock = threading.Lock()
        self._wakeup = asyncio.Event()
        self._wakeup_wanted = False
        self._closed = False

    def put(self, msg: can.Message) -> None:
        """Add a frame (reader thread); drop and count it when the buffer is full."""
        if self.channel is not None:
            msg.channel = self.channel
        with self._lock:
            self.frames_total += 1
            if self._closed:
                return
            if len(self._buf) >= self.maxsize:
                self.drops += 1
                return
            self._buf.append(msg)
            if not self._wakeup_wanted:
                return
            self._wakeup_wanted = False
        _call_in_loop(self._loop, self._wakeup.set)

    async def _wait(self) -> None:
        while True:
            with self._lock:
                if self._buf or self._closed:
                    return
                # Clearing and asking for a wake-up under the lock means a frame put after
                # this point always schedules the wake-up.
                self._wakeup.clear()
                self._wakeup_wanted = True
            await self._wakeup.wait()

    async def get(self) -> can.Message:
        """Next frame; raises BusClosedError once closed and drained."""
        while True:
            # deque.popleft is atomic; the lock only guards the going-to-sleep handshake.
            try:
                return self._buf.popleft()
            except IndexError:
                pass
            await self._wait()
            with self._lock:
                if not self._buf and self._closed:
                    raise BusClosedError("frame source closed")

    async def get_batch(self, max_frames: int = 1000) -> list[can.Message]:
        """Up to max_frames frames, waiting for at least one; [] once closed and drained."""
        await self._wait()
        with self._lock:
            n = min(max_frames, len(self._buf))
            return [self._buf.popleft() for _ in range(n)]

    def clear(self) -> None:
        """Discard waiting frames and zero the counters (a consumer starting afresh)."""
        with self._lock:
            self._buf.clear()
            self.frames_total = 0
            self.drops = 0

    def qsize(self) -> int:
        """Frames waiting for a consumer."""
        return len(self._buf)

    @property
    def closed(self) -> bool:
        """Whether close() was called."""
        return self._closed

    def close(self) -> None:
        """Stop accepting frames and wake every waiting consumer (event-loop thread only)."""
        with self._lock:
            self._closed = True
        self._wakeup.set()


class HandoffListener(can.Listener):
    """Notifier listener that feeds a FrameHandoff and reports receive errors to the loop."""

    def __init__(
        self,
        handoff: FrameHandoff,
        loop: asyncio.AbstractEventLoop,
        on_error: Callable[[Exception], None],
    ) -> None:
        self._handoff = handoff
        self._loop = loop
        self._on_error = on_error
        # One Python call less per frame on the reader thread.
        self.on_message_received = handoff.put  # type: ignore[method-assign]

    def on_message_received(self, msg: can.Message) -> None:
        """Hand the frame over (reader thread)."""
        self._handoff.put(msg)

    def on_error(self, exc: Exception) -> None:
        """Report a receive error to the loop (reader thread)."""
        _call_in_loop(self._loop, self._on_error, exc)
        # A Notifier without a loop calls recv() again right after a handled error; pausing
        # here keeps a dead bus from spinning until the loop has torn it down.
        time.sleep(0.1)


class ClaimListener(can.Listener):
    """Hands address claims and requests (PGN 60928 / 59904), and transport-protocol frames
    (TP.CM / TP.DT) addressed to the gateway, to the loop (reader thread)."""

    def __init__(
        self,
        loop: asyncio.AbstractEventLoop,
        handle: Callable[[int, bytes], None],
        gateway_sa: int,
    ) -> None:
        self._loop = loop
        self._handle = handle
        self._gateway_sa = gateway_sa

    def on_message_received(self, msg: can.Message) -> None:
        can_id = msg.arbitration_id
        # A shift and a set test per frame: claims, requests and sessions with us are rare.
        pf = (can_id >> 16) & 0xFF
        if pf in (0xEE, 0xEA) or (pf in (0xEC, 0xEB) and (can_id >> 8) & 0xFF == self._gateway_sa):
            if msg.is_extended_id and not msg.is_error_frame and not msg.is_remote_frame:
                _call_in_loop(self._loop, self._handle, can_id, bytes(msg.data))


@dataclasses.dataclass(frozen=True, slots=True)
class BusStatus:
    """A snapshot of one bus for health pages and metrics."""

    name: str
    state: BusState
    since: float
    last_error: str | None
    last_error_at: float | None
    opened_at: float | None
    reconnects: int
    frames_total: int
    frames_per_s: float
    drops: int
    queued: int
    # The gateway's J1939 address claim on this bus, when claiming is on (eqgw.protocol).
    address_claim: str | None = None
    # A socketcand link that took frames while nothing arrived for `stall_after_s`: sends are
    # refused until a frame arrives again.
    stalled: bool = False
    frames_handed: int = 0
    # The gateway's answers to other nodes (J1939-21): NACKs to requests, RTS/CTS sessions.
    answers: dict[str, int] = dataclasses.field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        """Plain dict for JSON."""
        return dataclasses.asdict(self)


def _socketcand_socket(bus: can.BusABC) -> socket.socket | None:
    # python-can keeps the TCP socket private; it is the only way to see the server hang up,
    # because its recv() turns end-of-stream into "no message" forever.
    sock = getattr(bus, "_SocketCanDaemonBus__socket", None)
    return sock if isinstance(sock, socket.socket) else None


def _dead_connection_reason(bus: can.BusABC) -> str | None:
    """Why a bus's connection is dead, or None when it looks alive or cannot be checked."""
    sock = _socketcand_socket(bus)
    if sock is None:
        return None
    try:
        peeked = sock.recv(1, socket.MSG_PEEK | socket.MSG_DONTWAIT)
    except (BlockingIOError, InterruptedError):
        return None
    except OSError as exc:
        return f"socketcand connection lost: {describe(exc)}"
    return None if peeked else "socketcand server closed the connection"


def _enable_keepalive(sock: socket.socket) -> None:
    """Let the kernel notice a socketcand server that vanished without closing the socket."""
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_KEEPALIVE, 1)
    for name, value in (
        ("TCP_KEEPIDLE", 5),
        ("TCP_KEEPINTVL", 2),
        ("TCP_KEEPCNT", 3),
        ("TCP_USER_TIMEOUT", 15_000),
    ):
        option = getattr(socket, name, None)
        if option is not None:
            sock.setsockopt(socket.IPPROTO_TCP, option, value)


def _close_half_open_socketcand(exc: BaseException) -> None:
    """Close the socket of a socketcand bus whose constructor failed after connecting."""
    # python-can's constructor raises on a refused handshake without closing its socket; the
    # half-built bus is only reachable through the traceback.
    tb = exc.__traceback__
    while tb is not None:
        candidate = tb.tb_frame.f_locals.get("self")
        if isinstance(candidate, SocketCanDaemonBus):
            sock = _socketcand_socket(candidate)
            if sock is not None:
                sock.close()
        tb = tb.tb_next


def _probe_tcp(host: object, port: object) -> None:
    """Fail fast when a socketcand server does not accept connections."""
    # python-can retries a refused connect in a tight loop for 10 s, logging each attempt.
    if not isinstance(host, str) or not isinstance(port, int):
        raise BusOpenError("socketcand needs options host (str) and port (int)")
    try:
        with socket.create_connection((host, port), timeout=3.0):
            pass
    except OSError as exc:
        raise BusOpenError(f"socketcand server {host}:{port} unreachable: {describe(exc)}") from exc


DEFAULT_OPEN_LIMIT = 16


class OpenGate:
    """At most `limit` buses of this process opening at once (a TCP connect and the socketcand
    handshake each): hundreds of buses on one socketcand server, all opening together after a
    start or a server restart, overflow its accept queue, time out and retry together. Every
    BusReader of one event loop shares one gate (`open_gate()`) unless given its own."""

    def __init__(self, limit: int = DEFAULT_OPEN_LIMIT) -> None:
        if limit < 1:
            raise ValueError("an open gate's limit is at least 1")
        self.limit = limit
        self.opening = 0
        self.max_opening = 0  # the most opens seen at once (for tests and benches)
        self._waiters: collections.deque[asyncio.Future[None]] = collections.deque()

    @contextlib.asynccontextmanager
    async def slot(self) -> AsyncIterator[None]:
        """Hold one of the `limit` places while opening (waiting, first come first served)."""
        while self.opening >= self.limit:
            waiter = asyncio.get_running_loop().create_future()
            self._waiters.append(waiter)
            try:
                await waiter
            except BaseException:
                if waiter.done() and not waiter.cancelled():
                    self._wake_next()  # woken, then cancelled: pass the place on
                raise
            finally:
                with contextlib.suppress(ValueError):
                    self._waiters.remove(waiter)
        self.opening += 1
        self.max_opening = max(self.max_opening, self.opening)
        try:
            yield
        finally:
            self.opening -= 1
            self._wake_next()

    def _wake_next(self) -> None:
        while self._waiters:
            waiter = self._waiters.popleft()
            if not waiter.done():
                waiter.set_result(None)
                return


_gates: weakref.WeakKeyDictionary[asyncio.AbstractEventLoop, OpenGate] = weakref.WeakKeyDictionary()


def open_gate() -> OpenGate:
    """The running event loop's shared gate (created with DEFAULT_OPEN_LIMIT; the gateway
    sets its limit from `bus_open_concurrency`)."""
    loop = asyncio.get_running_loop()
    gate = _gates.get(loop)
    if gate is None:
        gate = _gates[loop] = OpenGate()
    return gate


def open_bus(config: BusConfig) -> can.BusABC:
    """Open the python-can bus a BusConfig describes (blocking; run it in a thread)."""
    kwargs: dict[str, Any] = dict(config.options)
    if config.bitrate is not None:
        kwargs.setdefault("bitrate", config.bitrate)
    if config.interface == "socketcand":
        _probe_tcp(kwargs.get("host"), kwargs.get("port"))
    try:
        bus = can.Bus(interface=config.interface, channel=config.channel, **kwargs)
    except Exception as exc:
        _close_half_open_socketcand(exc)
        raise BusOpenError(
            f"{config.interface} channel {config.channel!r}: {describe(exc)}"
        ) from exc
    sock = _socketcand_socket(bus)
    if sock is not None:
        _enable_keepalive(sock)
    return bus


def _close_bus(bus: can.BusABC, notifier: can.Notifier | None) -> None:
    """Stop the reader thread, then the bus (blocking)."""
    try:
        if notifier is not None:
            notifier.stop(timeout=NOTIFIER_POLL_S * 10)
    finally:
        try:
            bus.shutdown()
        except Exception as exc:
            log.warning("shutting down %s failed: %s", bus.channel_info, describe(exc))


class ThreadRunner:
    """Runs blocking calls in short-lived threads and remembers them until they end."""

    def __init__(self, loop: asyncio.AbstractEventLoop, name: str) -> None:
        self._loop = loop
        self._name = name
        self._running: set[asyncio.Future[None]] = set()

    def run(
        self,
        fn: Callable[[], T],
        *,
        what: str,
        on_abandoned: Callable[[T], None] | None = None,
    ) -> asyncio.Future[T]:
        """Start fn in a thread; on_abandoned gets its result if the future was cancelled."""
        # Dedicated threads rather than an executor: an executor's idle workers outlive the
        # reader, and a call stuck in a driver would hold up every later call behind it.
        loop = self._loop
        result: asyncio.Future[T] = loop.create_future()
        finished: asyncio.Future[None] = loop.create_future()
        self._running.add(finished)
        finished.add_done_callback(self._running.discard)

        def deliver(ok: bool, value: Any) -> None:
            if result.cancelled():
                if ok and on_abandoned is not None:
                    self.run(functools.partial(on_abandoned, value), what=f"discard {what}")
            elif ok:
                result.set_result(value)
            else:
                result.set_exception(value)
            finished.set_result(None)

        def body() -> None:
            try:
                value: Any = fn()
                ok = True
            except BaseException as exc:
                value, ok = exc, False
            _call_in_loop(loop, deliver, ok, value)

        threading.Thread(target=body, name=f"{self._name}: {what}", daemon=True).start()
        return result

    async def join(self, timeout: float) -> bool:
        """Wait for every started thread to finish; False if some are still running."""
        deadline = time.monotonic() + timeout
        while self._running:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                return False
            await asyncio.wait(set(self._running), timeout=remaining)
        return True


class BusReader:
    """Reads one configured bus into asyncio, reopening it with backoff whenever it fails."""

    def __init__(
        self,
        config: BusConfig,
        *,
        queue_size: int = 10000,
        backoff: tuple[float, float] = (0.5, 30.0),
        open_timeout: float = 20.0,
        send_timeout: float = 5.0,
        liveness_interval: float = 0.5,
        rate_window: float = 5.0,
        stable_after: float = 10.0,
        gate: OpenGate | None = None,
    ) -> None:
        if not 0 < backoff[0] <= backoff[1]:
            raise ValueError("backoff is (first delay, longest delay), 0 < first <= longest")
        if queue_size < 1:
            raise ValueError("queue_size must be at least 1")
        self.config = config
        self.queue_size = queue_size
        self.backoff = backoff
        self.open_timeout = open_timeout
        self.send_timeout = send_timeout
        self.liveness_interval = liveness_interval
        self.rate_window = rate_window
        # A connection that lasted this long resets the backoff; shorter ones keep growing it,
        # so a bus that opens and fails at once is not reopened in a tight loop.
        self.stable_after = stable_after
        self._gate = gate  # None: the event loop's shared gate, taken at start()
        self._state: BusState = "closed"
        self._since = time.time()
        self._last_error: str | None = None
        self._last_error_at: float | None = None
        self._opened_at: float | None = None
        self._ever_opened = False
        self._reconnects = 0
        self._loop: asyncio.AbstractEventLoop | None = None
        self._handoff: FrameHandoff | None = None
        self._threads: ThreadRunner | None = None
        self._bus: can.BusABC | None = None
        self._generation = 0
        self._failure: asyncio.Future[str] | None = None
        self._opened = asyncio.Event()
        self._tx_lock = asyncio.Lock()
        self._tasks: list[asyncio.Task[None]] = []
        self._samples: collections.deque[tuple[float, int]] = collections.deque()
        self._stopped = False
        # J1939 address claim (on unless the bus opts out): every transmission waits for, and
        # needs, the claim.
        name = config.address_claim_name
        self._claimer = None if name is None else AddressClaimer(name, config.gateway_sa)
        self._claim_out: asyncio.Queue[tuple[int, bytes]] | None = None
        # The gateway's answers to requests and RTS/CTS sessions addressed to it (J1939-21).
        self.responder = GatewayResponder(config.gateway_sa)
        # False while fenced (app/cluster): nothing at all is sent, claims and answers included.
        self._transmit = True
        # Stall detection (socketcand): when a frame was last seen arriving, and since when
        # sends are refused because none did.
        self._rx_seen = 0
        self._rx_at = time.monotonic()
        self._stalled_since: float | None = None
        self._frames_handed = 0

    @property
    def name(self) -> str:
        """The bus name frames are tagged with (`msg.channel`)."""
        return self.config.name

    @property
    def gateway_sa(self) -> int:
        """The gateway's own J1939 source address on this bus."""
        return self.config.gateway_sa

    @property
    def bus(self) -> can.BusABC | None:
        """The python-can bus while open (for diagnostics; send through BusWriter)."""
        return self._bus

    @property
    def state(self) -> BusState:
        """Current connection state."""
        return self._state

    async def start(self) -> None:
        """Start reading in the background; returns at once, the bus opens asynchronously."""
        if self._tasks or self._stopped:
            raise RuntimeError(f"bus reader {self.name} was already started")
        install_socketcand_log_filter()
        loop = asyncio.get_running_loop()
        self._loop = loop
        if self._gate is None:
            self._gate = open_gate()
        self._handoff = FrameHandoff(loop, self.queue_size, channel=self.name)
        self._threads = ThreadRunner(loop, f"eqgw bus {self.name}")
        self._set_state("connecting")
        self._sample()
        self._tasks = [
            asyncio.create_task(self._supervise(), name=f"bus {self.name}: supervise"),
            asyncio.create_task(self._watch(), name=f"bus {self.name}: watch"),
        ]
        self._claim_out = asyncio.Queue()
        self._tasks.append(
            asyncio.create_task(self._answer_claims(), name=f"bus {self.name}: claim")
        )

    async def stop(self, timeout: float = 10.0) -> None:
        """Close the bus and end iteration; waits for every thread it started."""
        if self._stopped:
            return
        self._stopped = True
        # The supervisor closes the bus on its way out.
        for task in self._tasks:
            await cancel_and_wait(task)
        if self._handoff is not None:
            self._handoff.close()
        if self._threads is not None and not await self._threads.join(timeout):
            log.warning("bus %s: a driver call is still blocked after %.0f s", self.name, timeout)
        self._set_state("closed")

    async def __aenter__(self) -> BusReader:
        await self.start()
        return self

    async def __aexit__(self, *exc_info: object) -> None:
        await self.stop()

    async def wait_open(self, timeout: float | None = None) -> None:
        """Return once the bus is open; raises TimeoutError after timeout seconds."""
        async with asyncio.timeout(timeout):
            await self._opened.wait()

    def _require_started(self) -> FrameHandoff:
        if self._handoff is None:
            raise BusClosedError(f"bus reader {self.name} was not started")
        return self._handoff

    async def get(self) -> can.Message:
        """Next frame (bus timestamp, `channel` = bus name); BusClosedError once stopped."""
        return await self._require_started().get()

    async def get_batch(self, max_frames: int = 1000) -> list[can.Message]:
        """Up to max_frames waiting frames, at least one; [] once stopped and drained."""
        return await self._require_started().get_batch(max_frames)

    def __aiter__(self) -> AsyncIterator[can.Message]:
        return self

    async def __anext__(self) -> can.Message:
        handoff = self._require_started()
        try:
            return handoff._buf.popleft()  # the common case, without another coroutine
        except IndexError:
            pass
        try:
            return await handoff.get()
        except BusClosedError:
            raise StopAsyncIteration from None

    def status(self) -> BusStatus:
        """Current state, last error and traffic figures."""
        handoff = self._handoff
        total = handoff.frames_total if handoff else 0
        return BusStatus(
            name=self.name,
            state=self._state,
            since=self._since,
            last_error=self._last_error,
            last_error_at=self._last_error_at,
            opened_at=self._opened_at,
            reconnects=self._reconnects,
            frames_total=total,
            frames_per_s=self._rate(total),
            drops=handoff.drops if handoff else 0,
            queued=handoff.qsize() if handoff else 0,
            address_claim=self._claimer.describe() if self._claimer is not None else None,
            stalled=self._stalled_since is not None,
            frames_handed=self._frames_handed,
            answers=dataclasses.asdict(self.responder.stats),
        )

    def set_transmit(self, enabled: bool) -> None:
        """Allow or stop every transmission on this bus (a fenced gateway stops: another one
        may hold the bus). Allowed again, the address is claimed again first."""
        if enabled == self._transmit:
            return
        self._transmit = enabled
        log.info("bus %s: transmission %s", self.name, "allowed" if enabled else "stopped")
        claimer, out = self._claimer, self._claim_out
        if enabled and self._state == "open" and claimer is not None and out is not None:
            for frame in claimer.start(time.monotonic()):
                out.put_nowait(frame)

    def may_transmit(self) -> bool:
        """Whether the gateway may transmit on this bus now (open, and its claim held)."""
        if self._state != "open" or not self._transmit:
            return False
        return self._claimer is None or self._claimer.may_transmit(time.monotonic())

    @property
    def stall_after(self) -> float | None:
        """Receive silence (s) after which a socketcand link taking frames counts as stalled."""
        if self.config.interface != "socketcand" or not self.config.stall_after_s:
            return None
        return self.config.stall_after_s

    def _rx_age(self, now: float) -> float:
        """Seconds since a frame was last seen arriving (or the bus opened)."""
        total = self._handoff.frames_total if self._handoff is not None else 0
        if total != self._rx_seen:
            self._rx_seen = total
            self._rx_at = now
        return now - self._rx_at

    def _stall_reason(self) -> str | None:
        limit = self.stall_after
        if limit is None:
            return None
        now = time.monotonic()
        age = self._rx_age(now)
        if age < limit:
            return None
        reason = (
            f"link stalled: nothing received for {age:.0f} s while sending; "
            "frames are held back until it drains"
        )
        if self._stalled_since is None:
            self._stalled_since = now
            self._record_error(reason)
        return reason

    async def send_message(self, msg: can.Message, *, deadline: float | None = None) -> None:
        """Transmit one frame on the open bus (the writer's path; use BusWriter).

        With address claiming on, nothing is sent without the claim: during the claim's
        250 ms wait the frame waits; a lost claim is BusNotOpenError.
        """
        claimer = self._claimer
        if claimer is not None and self._state == "open":  # else _send says why it is not
            # The wait restarts if the claim frame leaves later than it was queued.
            while 0.0 < (wait := claimer.wait_s(time.monotonic())) <= CLAIM_WAIT_S:
                await asyncio.sleep(wait)
            if not claimer.may_transmit(time.monotonic()):
                raise BusNotOpenError(f"bus {self.name}: no J1939 {claimer.describe()}")
        await self._send(msg, deadline=deadline)

    async def _send(self, msg: can.Message, *, deadline: float | None = None) -> None:
        async with self._tx_lock:
            bus = self._bus
            if bus is None or self._state != "open" or self._threads is None:
                raise BusNotOpenError(self._not_open_reason())
            if not self._transmit:
                raise BusNotOpenError(f"bus {self.name}: transmission stopped (fenced)")
            timeout = self.send_timeout
            if deadline is not None:
                budget = deadline - time.time()
                if budget <= 0:
                    raise BusSendError(f"bus {self.name}: not sent, its deadline passed")
                timeout = min(timeout, budget)
            stalled = self._stall_reason()
            if stalled is not None:
                raise BusStalledError(f"bus {self.name}: {stalled}")
            generation = self._generation
            sending = self._threads.run(
                functools.partial(bus.send, msg, timeout=timeout), what="send"
            )
            # From here the frame may leave whatever happens to this call.
            self._frames_handed += 1
            try:
                # Not asyncio.wait_for: on 3.11 it drops a cancel that lands as the send
                # finishes, and the caller's task then never ends.
                async with asyncio.timeout(self.send_timeout):
                    await sending
            except TimeoutError as exc:
                reason = f"send blocked for more than {self.send_timeout:g} s"
                self._connection_failed(generation, reason)
                raise BusSendError(f"bus {self.name}: {reason}", handed=True) from exc
            except OSError as exc:
                # A broken TCP connection (socketcand) or a vanished adapter: reopen the bus.
                self._connection_failed(generation, f"send failed: {describe(exc)}")
                raise BusSendError(f"bus {self.name}: {describe(exc)}", handed=True) from exc
            except can.CanError as exc:
                # The driver refused the frame (its transmit queue full, an error state).
                self._frames_handed -= 1
                raise BusSendError(f"bus {self.name}: {describe(exc)}") from exc

    def _not_open_reason(self) -> str:
        reason = f"bus {self.name} is {self._state}"
        if self._last_error:
            reason += f" (last error: {self._last_error})"
        return reason

    # -- internals ---------------------------------------------------------------------------

    def _set_state(self, state: BusState) -> None:
        if state != self._state:
            log.debug("bus %s: %s -> %s", self.name, self._state, state)
            self._state = state
            self._since = time.time()
        if state == "open":
            self._opened.set()
        else:
            self._opened.clear()

    def _record_error(self, reason: str) -> None:
        if reason != self._last_error:
            log.warning("bus %s: %s", self.name, reason)
        else:
            log.debug("bus %s: %s (again)", self.name, reason)
        self._last_error = reason
        self._last_error_at = time.time()

    def _connection_failed(self, generation: int, reason: str) -> None:
        # Errors from a connection that was already replaced must not end the new one.
        failure = self._failure
        if generation == self._generation and failure is not None and not failure.done():
            failure.set_result(reason)

    def _on_receive_error(self, generation: int, exc: Exception) -> None:
        self._connection_failed(generation, f"receive failed: {describe(exc)}")

    async def _supervise(self) -> None:
        failures = 0
        while True:
            self._set_state("connecting")
            try:
                bus = await self._open()
            except asyncio.CancelledError:
                raise
            except Exception as exc:
                self._record_error(f"open failed: {describe(exc)}")
                failures += 1
                await self._back_off(failures)
                continue
            opened = time.monotonic()
            try:
                reason = await self._serve(bus)
            except asyncio.CancelledError:
                raise
            except Exception as exc:
                reason = f"bus failed: {describe(exc)}"
            self._record_error(reason)
            if time.monotonic() - opened >= self.stable_after:
                failures = 0
            failures += 1
            await self._back_off(failures)

    async def _open(self) -> can.BusABC:
        assert self._threads is not None and self._gate is not None
        # The wait for a place does not count against the open's own timeout.
        async with self._gate.slot():
            opening = self._threads.run(
                functools.partial(open_bus, self.config),
                what="open",
                on_abandoned=lambda bus: _close_bus(bus, None),
            )
            try:
                async with asyncio.timeout(self.open_timeout):
                    return await opening
            except TimeoutError as exc:
                raise BusOpenError(f"opening took longer than {self.open_timeout:g} s") from exc

    async def _serve(self, bus: can.BusABC) -> str:
        """Read from an open bus until it fails; returns why, always closing the bus."""
        assert self._loop is not None and self._handoff is not None and self._threads is not None
        self._generation += 1
        generation = self._generation
        failure: asyncio.Future[str] = self._loop.create_future()
        self._failure = failure
        listener = HandoffListener(
            self._handoff, self._loop, functools.partial(self._on_receive_error, generation)
        )
        notifier: can.Notifier | None = None
        try:
            listeners: list[can.Listener] = [
                listener,
                ClaimListener(self._loop, self._on_claim_frame, self.config.gateway_sa),
            ]
            notifier = can.Notifier(bus, listeners, timeout=NOTIFIER_POLL_S)
            self._bus = bus
            self._opened_at = time.time()
            if self._ever_opened:
                self._reconnects += 1
            self._ever_opened = True
            self._rx_seen = self._handoff.frames_total
            self._rx_at = time.monotonic()
            self._stalled_since = None
            self._set_state("open")
            log.info("bus %s: open (%s)", self.name, bus.channel_info)
            if self._claimer is not None and self._claim_out is not None:
                # Every (re)open claims the address again, before anything else is sent.
                for frame in self._claimer.start(time.monotonic()):
                    self._claim_out.put_nowait(frame)
            return await failure
        finally:
            self._bus = None
            self._failure = None
            self._stalled_since = None
            closing = self._threads.run(functools.partial(_close_bus, bus, notifier), what="close")
            # Shielded so a stop() arriving now still lets the close finish before it returns.
            await asyncio.shield(closing)

    def _on_claim_frame(self, can_id: int, data: bytes) -> None:
        out = self._claim_out
        if out is None:
            return
        # Answers to other nodes go out only while the gateway may transmit (holds its
        # address, not fenced); the responder follows their sessions all the same.
        answers = self.responder.on_frame(can_id, data, time.monotonic())
        if answers and self.may_transmit():
            for frame in answers:
                out.put_nowait(frame)
        elif answers:
            self.responder.stats.withheld += len(answers)
        claimer = self._claimer
        if claimer is None:
            return
        before = claimer.state
        for frame in claimer.on_frame(can_id, data, time.monotonic()):
            if claimer.is_cannot_claim(frame) and self._loop is not None:
                # J1939-81: "cannot claim" goes out after a random 0..153 ms.
                self._loop.call_later(claimer.cannot_claim_delay(), out.put_nowait, frame)
            else:
                out.put_nowait(frame)
        if claimer.state == "lost" and before != "lost":
            log.warning(
                "bus %s: %s; the gateway stops transmitting on this bus until it reopens",
                self.name,
                claimer.describe(),
            )

    async def _answer_claims(self) -> None:
        """Sends the claim and the answers to other nodes (they bypass the claim check,
        which was made when they were queued; nothing else may)."""
        assert self._claim_out is not None
        while True:
            can_id, data = await self._claim_out.get()
            msg = can.Message(arbitration_id=can_id, data=data, is_extended_id=True, is_rx=False)
            try:
                await self._send(msg)
                claimer = self._claimer
                if (
                    claimer is not None
                    and can_id & 0xFF == claimer.address
                    and ((can_id >> 16) & 0xFF == 0xEE)
                ):
                    claimer.claim_sent(time.monotonic())
            except asyncio.CancelledError:
                raise
            except Exception as exc:
                # The bus is down or reopening: its next open claims again.
                log.info("bus %s: address claim not sent: %s", self.name, describe(exc))

    async def _back_off(self, failures: int) -> None:
        first, longest = self.backoff
        # Jitter spreads the reconnects of many buses after one server restart: each waits
        # between half and all of its delay, so they do not come back in one burst.
        delay = backoff_delay(failures, first, longest)
        self._set_state("backoff")
        log.info("bus %s: retrying in %.1f s", self.name, delay)
        await asyncio.sleep(delay)

    async def _watch(self) -> None:
        while True:
            await asyncio.sleep(self.liveness_interval)
            self._sample()
            aborts = self.responder.expire(time.monotonic())
            if aborts and self._claim_out is not None and self.may_transmit():
                for frame in aborts:
                    self._claim_out.put_nowait(frame)
            elif aborts:
                self.responder.stats.withheld += len(aborts)
            # Every tick, so a send sees how long ago a frame arrived to within this interval.
            age = self._rx_age(time.monotonic())
            limit = self.stall_after
            if self._stalled_since is not None and limit is not None and age < limit:
                log.warning("bus %s: link drains again, sending resumes", self.name)
                self._stalled_since = None
            bus = self._bus
            if bus is not None:
                reason = _dead_connection_reason(bus)
                if reason is not None:
                    self._connection_failed(self._generation, reason)

    def _sample(self) -> None:
        if self._handoff is None:
            return
        now = time.monotonic()
        self._samples.append((now, self._handoff.frames_total))
        while self._samples and now - self._samples[0][0] > self.rate_window:
            self._samples.popleft()

    def _rate(self, total: int) -> float:
        if not self._samples:
            return 0.0
        then, then_total = self._samples[0]
        elapsed = time.monotonic() - then
        return (total - then_total) / elapsed if elapsed > 0 else 0.0
