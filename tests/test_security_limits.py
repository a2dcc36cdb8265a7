"""Limits before work, against a real `eqgw serve` process over real sockets: bodies past a
route's bound, bodies of unauthenticated requests, headers sent too slowly, a websocket client
flooding its control messages."""

from __future__ import annotations

import re
import socket
import time
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest
from websockets.exceptions import ConnectionClosed
from websockets.sync.client import connect as ws_connect

from tests.proc_helpers import Process, eqgw, wait_until
from tests.support import web

SERVING = re.compile(r"serving on http://([\d.]+):(\d+)")
FIRST_KEY = re.compile(r"^\s+(eqgw_\S+)$", re.M)
BOUND = 64 * 1024
COMMANDS = "/api/v1/vehicles/SIM-001/commands"


class Gateway:
    def __init__(self, host: str, port: int, admin: str) -> None:
        self.host, self.port, self.admin = host, port, admin

    def connect(self, timeout: float = 20.0) -> socket.socket:
        sock = socket.create_connection((self.host, self.port), timeout=timeout)
        return sock


@pytest.fixture(scope="module")
def gateway(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Gateway]:
    tmp: Path = tmp_path_factory.mktemp("limits")
    env = {
        "EQGW_DATABASE_URL": f"sqlite:///{tmp / 'eqgw.db'}",
        "EQGW_API_MAX_BODY_BYTES": str(BOUND),
        "EQGW_API_HEADER_TIMEOUT_S": "1",
        "EQGW_API_BODY_TIMEOUT_S": "2",
        "EQGW_API_WS_CONTROL_QUEUE": "4",
    }
    proc = Process(eqgw("serve", "--simulate", "1", "--port", "0"), tmp, env)
    try:
        m = proc.wait_line(SERVING, timeout=90)
        key = FIRST_KEY.search(proc.output())
        assert key is not None, proc.output()
        gw = Gateway(m.group(1), int(m.group(2)), key.group(1))

        def listening() -> bool:  # "serving on" is said just before uvicorn listens
            try:
                gw.connect(timeout=1).close()
            except OSError:
                return False
            return True

        wait_until(listening, 30, "the gateway listening")
        yield gw
    finally:
        proc.stop()


def _response(sock: socket.socket) -> tuple[int, bytes]:
    """The status and what came of the response (until the headers end, at least)."""
    data = b""
    while b"\r\n\r\n" not in data:
        chunk = sock.recv(65536)
        if not chunk:
            break
        data += chunk
    status = int(data.split(b" ", 2)[1]) if data.startswith(b"HTTP/1.1 ") else 0
    return status, data


def test_a_declared_body_past_the_bound_is_refused_unread(gateway: Gateway) -> None:
    """200 MB announced: the 413 comes back after the headers alone (nothing else is sent)."""
    with gateway.connect() as sock:
        sock.sendall(
            f"POST {COMMANDS} HTTP/1.1\r\nHost: x\r\nAuthorization: Bearer {gateway.admin}\r\n"
            f"Content-Type: application/json\r\nContent-Length: {200 * 1024 * 1024}\r\n\r\n"
            "{".encode()
        )
        status, data = _response(sock)
    assert status == 413, data


def test_an_unauthenticated_body_is_never_read(gateway: Gateway) -> None:
    """A streamed body without a key: the 401 comes while the body is still being sent."""
    with gateway.connect() as sock:
        sock.sendall(
            f"POST {COMMANDS} HTTP/1.1\r\nHost: x\r\nContent-Type: application/json\r\n"
            "Transfer-Encoding: chunked\r\n\r\n".encode()
        )
        sock.sendall(b"1000\r\n" + b" " * 4096 + b"\r\n")  # one chunk of an endless body
        status, data = _response(sock)
    assert status == 401, data


def test_a_streamed_body_is_cut_at_the_bound(gateway: Gateway) -> None:
    with gateway.connect() as sock:
        sock.sendall(
            f"POST {COMMANDS} HTTP/1.1\r\nHost: x\r\nAuthorization: Bearer {gateway.admin}\r\n"
            "Content-Type: application/json\r\nTransfer-Encoding: chunked\r\n\r\n".encode()
        )
        chunk = b"2000\r\n" + b" " * 8192 + b"\r\n"
        for _ in range(BOUND // 8192 + 2):  # past the bound, then no more
            sock.sendall(chunk)
        status, data = _response(sock)
    assert status == 413, data


def test_a_body_that_never_arrives_is_a_408(gateway: Gateway) -> None:
    """An authenticated request announcing 100 bytes and sending 10: a 408 (the body deadline
    is 2 s here; the socket waits 20 s)."""
    with gateway.connect() as sock:
        sock.sendall(
            f"POST {COMMANDS} HTTP/1.1\r\nHost: x\r\nAuthorization: Bearer {gateway.admin}\r\n"
            'Content-Type: application/json\r\nContent-Length: 100\r\n\r\n{"jump_sta'.encode()
        )
        status, data = _response(sock)
    assert status == 408, data


def test_headers_sent_too_slowly_end_the_connection(gateway: Gateway) -> None:
    """Slowloris: a header byte every 0.2 s; the server closes the connection (its header
    deadline is 1 s here) long before the 15 s this test gives it."""
    with gateway.connect(timeout=1.0) as sock:
        sock.sendall(b"GET /healthz HTTP/1.1\r\nHost: x\r\n")
        closed = False
        deadline = time.monotonic() + 15
        while time.monotonic() < deadline and not closed:
            try:
                sock.sendall(b"X")
                time.sleep(0.2)
                sock.setblocking(False)
                try:
                    closed = sock.recv(1024) == b""
                except BlockingIOError:
                    pass
                finally:
                    sock.setblocking(True)
            except (BrokenPipeError, ConnectionResetError):
                closed = True
    assert closed, "the server still holds a connection whose headers never end"


def test_a_websocket_flooding_its_control_messages_is_closed(gateway: Gateway) -> None:
    url = f"ws://{gateway.host}:{gateway.port}/api/v1/ws?vehicles=SIM-001"
    headers = {"Authorization": f"Bearer {gateway.admin}"}
    with ws_connect(url, additional_headers=headers, open_timeout=20) as ws:
        assert '"snapshot"' in str(ws.recv(timeout=20))
        message = '{"type": "subscribe", "vehicles": ["SIM-001"]}'
        try:
            for _ in range(50_000):
                ws.send(message)
        except ConnectionClosed:
            pass
        deadline = time.monotonic() + 60
        with pytest.raises(ConnectionClosed):
            while time.monotonic() < deadline:
                ws.recv(timeout=max(0.1, deadline - time.monotonic()))
    assert ws.close_code == 1008, (ws.close_code, ws.close_reason)
    assert "too many messages" in (ws.close_reason or "")


SHARED_RATE = 4


@pytest.fixture
def two_gateways(tmp_path: Path, db_url: str) -> Iterator[tuple[str, str, list[str]]]:
    """Two `eqgw serve` processes on one database (one PostgreSQL schema, or one SQLite file),
    a write limit of SHARED_RATE per 10 minutes; (base A, base B, two operator keys)."""
    from tests.cluster_helpers import operator_key

    keys = [operator_key(db_url, f"shared budget {i}") for i in range(2)]
    env = {
        "EQGW_DATABASE_URL": db_url,
        "EQGW_API_WRITE_RATE": str(SHARED_RATE),
        "EQGW_API_WRITE_WINDOW_S": "600",
    }
    procs = [Process(eqgw("serve", "--port", "0"), tmp_path, env) for _ in range(2)]
    try:
        bases = [f"http://{m[1]}:{m[2]}" for m in (p.wait_line(SERVING, 90) for p in procs)]

        def up(base: str) -> bool:
            try:
                return web.get(f"{base}/healthz", timeout=2).status_code == 200
            except httpx.HTTPError:
                return False

        for base in bases:
            wait_until(lambda: up(base), 30, f"{base} answering")  # noqa: B023
        yield bases[0], bases[1], keys
    finally:
        for p in procs:
            p.stop()


def _cancel(base: str, key: str, n: int) -> int:
    """Cancel a command that does not exist: a write counted against the key's limit, then a
    404 (or the 429 of the limit)."""
    r = web.delete(
        f"{base}/api/v1/commands/none-{n}", headers={"Authorization": f"Bearer {key}"}, timeout=60
    )
    assert r.status_code in (404, 429), r.text
    return r.status_code


def test_two_gateways_share_one_write_budget(two_gateways: tuple[str, str, list[str]]) -> None:
    """A key's writes through two gateways on one database count against one limit (before,
    each gateway kept its own count: twice the writes)."""
    a, b, (key, other) = two_gateways
    # Half of the limit on each, then the next on either is a 429.
    half = SHARED_RATE // 2
    assert [_cancel(a, key, i) for i in range(half)] == [404] * half
    assert [_cancel(b, key, i) for i in range(half)] == [404] * half
    assert _cancel(b, key, 99) == 429
    assert _cancel(a, key, 99) == 429
    # 3x the limit at once, half through each gateway: exactly the limit get through.
    from concurrent.futures import ThreadPoolExecutor

    jobs = [(a if i % 2 else b, i) for i in range(3 * SHARED_RATE)]
    with ThreadPoolExecutor(len(jobs)) as pool:
        codes = list(pool.map(lambda job: _cancel(job[0], other, job[1]), jobs))
    assert codes.count(404) == SHARED_RATE, codes
