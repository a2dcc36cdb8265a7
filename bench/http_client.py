"""A lean HTTP/1.1 keep-alive client for load tests: asyncio streams and httptools' C parser.

httpx parses responses in Python (h11); with 50 clients reading 100-300 kB bodies on the
same 2 cores as the server, the client, not the server, set the request rate. This client
only sends a GET and reads the response by its framing (the C parser), which costs a few
percent of that, so the figures measure the server.
"""

from __future__ import annotations

import asyncio

import httptools


class _Response:
    """What the parser collected of one response."""

    def __init__(self) -> None:
        self.status = 0
        self.size = 0
        self.done = False

    def on_body(self, body: bytes) -> None:
        self.size += len(body)

    def on_message_complete(self) -> None:
        self.done = True


class LeanClient:
    """One keep-alive connection; `get(path)` returns (status, body bytes)."""

    def __init__(self, host: str, port: int, headers: dict[str, str]) -> None:
        self.host, self.port = host, port
        extra = "".join(f"{k}: {v}\r\n" for k, v in headers.items())
        self._head = f"Host: {host}:{port}\r\n{extra}Connection: keep-alive\r\n\r\n"
        self._reader: asyncio.StreamReader | None = None
        self._writer: asyncio.StreamWriter | None = None

    async def get(self, path: str) -> tuple[int, int]:
        if self._writer is None or self._writer.is_closing():
            self._reader, self._writer = await asyncio.open_connection(self.host, self.port)
        reader, writer = self._reader, self._writer
        assert reader is not None
        writer.write(f"GET {path} HTTP/1.1\r\n{self._head}".encode())
        response = _Response()
        parser = httptools.HttpResponseParser(response)
        while not response.done:
            chunk = await reader.read(1 << 16)
            if not chunk:
                await self.close()
                raise ConnectionError("server closed the connection")
            parser.feed_data(chunk)
        response.status = parser.get_status_code()
        if not parser.should_keep_alive():
            await self.close()
        return response.status, response.size

    async def close(self) -> None:
        writer, self._writer = self._writer, None
        if writer is not None:
            writer.close()
            try:
                await writer.wait_closed()
            except (ConnectionError, OSError):
                pass
