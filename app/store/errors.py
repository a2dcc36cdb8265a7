"""Errors raised by the store layer."""


class StoreError(Exception):
    """Base of every store-layer error."""


class DatabaseUrlError(StoreError):
    """A database URL names no supported engine or driver."""


class DatabaseUnavailableError(StoreError):
    """The database cannot be reached or refuses writes (restart, lock, disk full)."""


class MigrationError(StoreError):
    """The schema cannot be brought to the current revision."""
