"""Where webhooks may be sent: public addresses only, unless a network is allowed.

A webhook URL is set by an admin through the API, so an unchecked one is a way into the
gateway's own network (loopback services, cloud metadata at 169.254.169.254, private hosts).
Every address a webhook's host resolves to must be global, or inside a network of the
`webhook_allow_networks` setting; the check runs when a webhook is saved and again at every
connection, on the addresses actually connected to (a name that resolves elsewhere later, DNS
rebinding, is refused then). Credentials in webhook URLs are redacted wherever a URL is shown.
"""

from __future__ import annotations

import asyncio
import functools
import ipaddress
import socket
import ssl
from collections.abc import Iterable
from typing import Any
from urllib.parse import parse_qsl, urlencode, urlsplit, urlunsplit

import httpcore
import httpx

# A setting's parser, kept here under its old name for the senders that use it.
from eqgw.config import parse_networks as parse_networks

IPAddress = ipaddress.IPv4Address | ipaddress.IPv6Address
IPNetwork = ipaddress.IPv4Network | ipaddress.IPv6Network
ALLOW_SETTING = "EQGW_WEBHOOK_ALLOW_NETWORKS"
REDACTED = "***"
# Hosts whose webhook URLs carry their credential as the last path segment.
_TOKEN_IN_PATH = ("hooks.slack.com", "discord.com", "discordapp.com", "webhook.office.com")


class DestinationRefused(httpcore.ConnectError):
    """A webhook destination outside what the gateway may reach (raised before connecting)."""


def refusal(address: IPAddress, allow: Iterable[IPNetwork] = ()) -> str | None:
    """Why `address` may not be reached, or None when it may."""
    ip: IPAddress = address
    if isinstance(ip, ipaddress.IPv6Address) and ip.ipv4_mapped is not None:
        ip = ip.ipv4_mapped
    if any(ip.version == net.version and ip in net for net in allow):
        return None
    if ip.is_global:
        return None
    kind = (
        "loopback"
        if ip.is_loopback
        else "link-local (cloud metadata)"
        if ip.is_link_local
        else "unspecified"
        if ip.is_unspecified
        else "multicast"
        if ip.is_multicast
        else "private"
        if ip.is_private
        else "not public"
    )
    return (
        f"destination {address} is {kind}; webhooks reach public addresses only, "
        f"unless its network is in {ALLOW_SETTING}"
    )


async def resolve(host: str, port: int) -> list[IPAddress]:
    """Every address `host` resolves to (a literal address is itself)."""
    try:
        return [ipaddress.ip_address(host.strip("[]"))]
    except ValueError:
        pass
    infos = await asyncio.get_running_loop().getaddrinfo(host, port, type=socket.SOCK_STREAM)
    seen: list[IPAddress] = []
    for *_, sockaddr in infos:
        ip = ipaddress.ip_address(str(sockaddr[0]).split("%")[0])
        if ip not in seen:
            seen.append(ip)
    return seen


async def check_url(url: str, allow: Iterable[IPNetwork]) -> str | None:
    """Why a webhook URL's host may not be reached, or None (a name that does not resolve
    now is let through: delivery checks again, and fails, until it does)."""
    parts = urlsplit(url)
    host = parts.hostname or ""
    try:
        port = parts.port or (443 if parts.scheme == "https" else 80)
    except ValueError:
        return "the URL's port is not a number"
    try:
        addresses = await resolve(host, port)
    except OSError:
        return None
    for ip in addresses:
        reason = refusal(ip, allow)
        if reason is not None:
            return reason
    return None


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


def redact_url(url: str, fmt: str | None = None) -> str:
    """`url` without its credentials: user and password, query values, and the token that
    Slack-style (and Teams connector) webhook URLs carry as their last path segment."""
    try:
        parts = urlsplit(url)
        host = parts.hostname or ""
        port = f":{parts.port}" if parts.port else ""
    except ValueError:
        return REDACTED
    shown_host = f"[{host}]" if ":" in host else host
    netloc = (f"{REDACTED}@" if parts.username or parts.password else "") + shown_host + port
    query = parts.query
    if query:
        query = urlencode([(k, REDACTED) for k, _ in parse_qsl(query, keep_blank_values=True)])
        query = query.replace("%2A%2A%2A", REDACTED)
    path = parts.path
    token_host = any(host == h or host.endswith("." + h) for h in _TOKEN_IN_PATH)
    if (fmt in ("slack", "teams") or token_host) and path.strip("/"):
        head, _, _tail = path.rstrip("/").rpartition("/")
        path = f"{head}/{REDACTED}"
    return urlunsplit((parts.scheme, netloc, path, query, ""))
