"""Errors raised by the protocol layer."""


class ProtocolError(Exception):
    """Base of every protocol-layer error."""


class DecodeError(ProtocolError):
    """A payload cannot be decoded (too short, unknown index, bad structure)."""


class EncodeError(ProtocolError):
    """Values cannot be encoded (unknown field, out of the raw range)."""
