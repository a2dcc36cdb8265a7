"""uvicorn's h11 protocol with a deadline on request headers (uvicorn has none).

uvicorn times out an idle keep-alive connection, but a client that sends a request's headers
slowly (slowloris: a byte now and then) holds its connection, and its memory, forever. Here
every request's headers must be complete within `header_timeout_s` of the connection opening
or of the request's first byte; past it the connection is closed.
"""

from __future__ import annotations

import asyncio
from typing import Any

import h11
from uvicorn.protocols.http.h11_impl import H11Protocol


def bounded_h11(header_timeout_s: float) -> type[H11Protocol]:
    """An H11Protocol class whose connections give up on headers after `header_timeout_s`."""

    class HeaderDeadlineH11(H11Protocol):
        _header_timer: asyncio.TimerHandle | None = None

        def connection_made(self, transport: Any) -> None:
            super().connection_made(transport)
            self._arm()

        def data_received(self, data: bytes) -> None:
            super().data_received(data)
            if self.transport.is_closing():
                self._disarm()
            elif self.conn.their_state is h11.IDLE:
                # Part of a request's headers (or nothing yet): the clock runs.
                if self._header_timer is None:
                    self._arm()
            else:
                self._disarm()  # the headers are in (body reads are bounded by the app)

        def connection_lost(self, exc: Exception | None) -> None:
            self._disarm()
            super().connection_lost(exc)

        def _arm(self) -> None:
            self._header_timer = self.loop.call_later(header_timeout_s, self._headers_late)

        def _disarm(self) -> None:
            if self._header_timer is not None:
                self._header_timer.cancel()
                self._header_timer = None

        def _headers_late(self) -> None:
            self._header_timer = None
            if self.conn.their_state is h11.IDLE and not self.transport.is_closing():
                self.transport.close()

    return HeaderDeadlineH11
