"""Errors raised by the bus layer (live buses, log replay, the socketcand server)."""

from __future__ import annotations


class BusError(Exception):
    """Base of every bus-layer error."""


class BusOpenError(BusError):
    """A bus could not be opened (driver missing, server unreachable, handshake refused)."""


class BusNotOpenError(BusError):
    """An operation needs an open bus but the bus is connecting, backing off or closed."""


class BusSendError(BusError):
    """A frame could not be transmitted on an open bus."""


class BusClosedError(BusError):
    """The reader was stopped; no more frames will arrive."""


class LogFileError(BusError):
    """A log file for replay is missing, of an unknown format or unreadable."""


class SocketcandServerError(BusError):
    """The socketcand server cannot start (address in use, bad bus mapping)."""
