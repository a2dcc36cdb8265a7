"""The HTTP client of webhook deliveries: httpx, connecting only where `refusal` allows.

Apart from the rules of eqgw.notify.destinations because it loads the HTTP stack (httpx and
httpcore, and what those load when installed: 0.1-0.3 s of CPU): a gateway loads it when it
first sends a webhook, not at its start."""

from __future__ import annotations

import functools
import ssl
from collections.abc import Iterable
from typing import Any

import httpcore
import httpx

from eqgw.notify.destinations import IPNetwork, refusal, resolve


class DestinationRefused(httpcore.ConnectError):
    """A webhook destination outside what the gateway may reach (raised before connecting)."""


class _GuardedBackend(httpcore.AsyncNetworkBackend):
    """httpcore's network backend, connecting only to addresses `refusal` lets through; it
    connects to the address it checked (never resolving the name a second time)."""

    def __init__(self, allow: tuple[IPNetwork, ...]) -> None:
        self.allow = allow
        self.inner = httpcore.AnyIOBackend()

    async def connect_tcp(
        self,
        host: str,
        port: int,
        timeout: float | None = None,
        local_address: str | None = None,
        socket_options: Iterable[Any] | None = None,
    ) -> httpcore.AsyncNetworkStream:
        try:
            addresses = await resolve(host, port)
        except OSError as exc:
            raise httpcore.ConnectError(f"cannot resolve {host}: {exc}") from exc
        for ip in addresses:
            reason = refusal(ip, self.allow)
            if reason is not None:
                raise DestinationRefused(reason)
        error: Exception | None = None
        for ip in addresses:
            try:
                return await self.inner.connect_tcp(
                    str(ip), port, timeout, local_address, socket_options
                )
            except httpcore.ConnectError as exc:
                error = exc
        raise error or httpcore.ConnectError(f"{host} has no address")

    async def connect_unix_socket(
        self, path: str, timeout: float | None = None, socket_options: Iterable[Any] | None = None
    ) -> httpcore.AsyncNetworkStream:
        raise DestinationRefused("webhooks do not use unix sockets")

    async def sleep(self, seconds: float) -> None:
        await self.inner.sleep(seconds)


@functools.cache
def tls_context() -> ssl.SSLContext:
    """The TLS settings of every webhook client of this process: the system's certificate
    authorities (certifi's bundle), nothing from the environment. Made once: loading the
    bundle is 20-30 ms of CPU, and a context serves any number of connections and clients."""
    return httpx.create_ssl_context(trust_env=False)


def guarded_client(allow: tuple[IPNetwork, ...]) -> httpx.AsyncClient:
    """An HTTP client for webhook deliveries: no redirects, no proxy from the environment,
    and connections only where `refusal` allows."""
    transport = httpx.AsyncHTTPTransport(verify=tls_context(), trust_env=False)
    pool = transport._pool
    # httpx has no parameter for the network backend: the same pool, with the guarded one.
    transport._pool = httpcore.AsyncConnectionPool(
        ssl_context=pool._ssl_context,
        max_connections=pool._max_connections,
        max_keepalive_connections=pool._max_keepalive_connections,
        keepalive_expiry=pool._keepalive_expiry,
        http1=True,
        http2=False,
        network_backend=_GuardedBackend(allow),
    )
    return httpx.AsyncClient(transport=transport, follow_redirects=False, trust_env=False)
