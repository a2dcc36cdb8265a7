"""HTTP calls from the tests to the gateways and servers they run: httpx's functions, with one
TLS context for the whole test process.

httpx builds a TLS context, the CA bundle loaded, for every client it makes, and `httpx.get`
makes a client per call: 15-20 ms of CPU each, for URLs that are plain HTTP. A test polling a
gateway's /readyz every 0.1 s spent a sixth of a core on them, and the suite, with many such
waits on two cores, over a minute of CPU. These take the same arguments; `verify` given wins.
A client per call stays (no connection outlives a call: tests stop and kill the servers).
"""

from __future__ import annotations

from typing import Any

import httpx

TLS = httpx.create_ssl_context()


def _tls(kwargs: dict[str, Any]) -> dict[str, Any]:
    kwargs.setdefault("verify", TLS)
    return kwargs


def request(method: str, url: str, **kwargs: Any) -> httpx.Response:
    return httpx.request(method, url, **_tls(kwargs))


def get(url: str, **kwargs: Any) -> httpx.Response:
    return httpx.get(url, **_tls(kwargs))


def post(url: str, **kwargs: Any) -> httpx.Response:
    return httpx.post(url, **_tls(kwargs))


def put(url: str, **kwargs: Any) -> httpx.Response:
    return httpx.put(url, **_tls(kwargs))


def patch(url: str, **kwargs: Any) -> httpx.Response:
    return httpx.patch(url, **_tls(kwargs))


def delete(url: str, **kwargs: Any) -> httpx.Response:
    return httpx.delete(url, **_tls(kwargs))


def stream(method: str, url: str, **kwargs: Any) -> Any:
    return httpx.stream(method, url, **_tls(kwargs))


def Client(**kwargs: Any) -> httpx.Client:
    return httpx.Client(**_tls(kwargs))


def AsyncClient(**kwargs: Any) -> httpx.AsyncClient:
    return httpx.AsyncClient(**_tls(kwargs))
