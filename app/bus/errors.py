"""Errors raised by the bus layer (live buses, log replay, the socketcand server)."""

from __future__ import annotations


class BusError(Exception):
    """Base of every bus-layer error."""


class BusOpenError(BusError):
    """A bus could not be opened (driver missing, server unreachable, handshake refused)."""


class BusNotOpenError(BusError):
    """An operation needs an open bus but the bus is connecting, backing off or closed."""


class BusSendError(BusError):
    """A frame could not be transmitted on an open bus.

    `handed`: whether the frame may have reached the interface all the same (a send that
    timed out or broke mid-way); False when it was never handed over."""

    def __init__(self, message: str, *, handed: bool = False) -> None:
        super().__init__(message)
        self.handed = handed


class BusStalledError(BusSendError):
    """The link does not drain (nothing received for a while as frames were sent): frames are
    no longer handed to it until it shows life again."""


class BusClosedError(BusError):
    """The reader was stopped; no more frames will arrive."""


class LogFileError(BusError):
    """A log file for replay is missing, of an unknown format or unreadable."""


class SocketcandServerError(BusError):
    """The socketcand server cannot start (address in use, bad bus mapping)."""
