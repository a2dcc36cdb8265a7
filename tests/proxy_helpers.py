"""A TCP proxy that can break the network the way networks break: `blackhole()` keeps every
connection open but forwards no byte in either direction (no reset, no FIN: a switch, a VPN
or a cloud failover dropping packets), new connections included; `restore()` ends it."""

from __future__ import annotations

import contextlib
import select
import socket
import threading
import time
from collections.abc import Iterator

from sqlalchemy.engine import make_url


class BlackholeProxy:
    """Listens on 127.0.0.1:`port` and forwards to `target`; one thread per direction."""

    def __init__(self, target: tuple[str, int]) -> None:
        self.target = target
        self._listener = socket.create_server(("127.0.0.1", 0))
        self.port: int = self._listener.getsockname()[1]
        self._open = threading.Event()  # set: bytes flow
        self._open.set()
        self._closed = False
        self._socks: list[socket.socket] = []
        self._lock = threading.Lock()
        self.blackholed_at: float | None = None
        self._acceptor = threading.Thread(target=self._accept, daemon=True, name="proxy-accept")
        self._acceptor.start()

    def url(self, database_url: str) -> str:
        """`database_url` with its host and port replaced by the proxy's."""
        return (
            make_url(database_url)
            .set(host="127.0.0.1", port=self.port)
            .render_as_string(hide_password=False)
        )

    def blackhole(self) -> float:
        """From now on nothing passes; returns the time (time.time()) it began."""
        self._open.clear()
        self.blackholed_at = time.time()
        return self.blackholed_at

    def restore(self) -> None:
        self._open.set()

    def close(self) -> None:
        with self._lock:
            self._closed = True
        self._open.set()
        # On Linux a close() does not wake an accept() blocked in another thread; a shutdown
        # does (EINVAL), and the accepting thread ends.
        with contextlib.suppress(OSError):
            self._listener.shutdown(socket.SHUT_RDWR)
        with contextlib.suppress(OSError):
            self._listener.close()
        self._acceptor.join(timeout=5)
        with self._lock:
            for s in self._socks:
                with contextlib.suppress(OSError):
                    s.close()

    def _accept(self) -> None:
        while not self._closed:
            try:
                client, _ = self._listener.accept()
            except OSError:
                return
            threading.Thread(target=self._serve, args=(client,), daemon=True).start()

    def _keep(self, sock: socket.socket) -> bool:
        """Track `sock` for close(); False (and closed) if the proxy is closing."""
        with self._lock:
            if self._closed:
                sock.close()
                return False
            self._socks.append(sock)
            return True

    def _serve(self, client: socket.socket) -> None:
        if not self._keep(client):
            return
        self._open.wait()  # accepted during a blackhole: the far side is never reached
        if self._closed:
            return
        try:
            upstream = socket.create_connection(self.target, timeout=10)
        except OSError:
            client.close()
            return
        upstream.settimeout(None)
        if not self._keep(upstream):
            return
        for a, b in ((client, upstream), (upstream, client)):
            threading.Thread(target=self._pump, args=(a, b), daemon=True).start()

    def _pump(self, src: socket.socket, dst: socket.socket) -> None:
        try:
            while not self._closed:
                if not self._open.is_set():
                    # Not reading: the bytes wait in the kernel, the sender sees no error.
                    self._open.wait(0.1)
                    continue
                ready, _, _ = select.select([src], [], [], 0.1)
                if not ready or not self._open.is_set():
                    continue
                data = src.recv(65536)
                if not data:
                    with contextlib.suppress(OSError):
                        dst.shutdown(socket.SHUT_WR)
                    return
                dst.sendall(data)
        except OSError:
            return


@contextlib.contextmanager
def blackhole_proxy(database_url: str) -> Iterator[BlackholeProxy]:
    """A proxy in front of the PostgreSQL server of `database_url`."""
    url = make_url(database_url)
    proxy = BlackholeProxy((url.host or "127.0.0.1", url.port or 5432))
    try:
        yield proxy
    finally:
        proxy.close()
