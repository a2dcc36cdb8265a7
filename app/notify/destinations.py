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
import ipaddress
import socket
from collections.abc import Iterable
from urllib.parse import parse_qsl, urlencode, urlsplit, urlunsplit

# A setting's parser, kept here under its old name for the senders that use it.
from eqgw.config import parse_networks as parse_networks

IPAddress = ipaddress.IPv4Address | ipaddress.IPv6Address
IPNetwork = ipaddress.IPv4Network | ipaddress.IPv6Network
ALLOW_SETTING = "EQGW_WEBHOOK_ALLOW_NETWORKS"
REDACTED = "***"
# Hosts whose webhook URLs carry their credential as the last path segment.
_TOKEN_IN_PATH = ("hooks.slack.com", "discord.com", "discordapp.com", "webhook.office.com")


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
