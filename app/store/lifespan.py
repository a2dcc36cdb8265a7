"""The database of a running gateway, as the lifespan's first part (see app/main.py)."""

from __future__ import annotations

import time
from collections.abc import AsyncIterator
from contextlib import AsyncExitStack, asynccontextmanager
from typing import TYPE_CHECKING

from sqlalchemy import Engine

from eqgw.store.engine import create_engine, database_deadline_scope, end_database_work_by

if TYPE_CHECKING:
    from eqgw.config import DatabaseSettings

# Of the shutdown's time, kept for the ingest's final flush (or its journal) at the end.
SHUTDOWN_WRITER_RESERVE_S = 2.5


class ShutdownClock:
    """When the lifespan's shutdown must be over. `begin()` when it starts: from then on
    every database call ends in time for the writer to journal its rows (a database that
    stops answering must not hold the stop past its bound), and `left()` is what remains."""

    def __init__(self, bound_s: float) -> None:
        self.bound_s = bound_s
        self.by: float | None = None  # monotonic

    def begin(self) -> None:
        self.by = time.monotonic() + self.bound_s
        end_database_work_by(self.by - SHUTDOWN_WRITER_RESERVE_S)

    def left(self, default: float = 30.0) -> float:
        """Seconds left of the shutdown (`default` before it began)."""
        return default if self.by is None else self.by - time.monotonic()


@asynccontextmanager
async def database(url: str, deadlines: DatabaseSettings) -> AsyncIterator[Engine]:
    """The engine (every PostgreSQL operation with its deadline), disposed at the end.

    The shutdown's database deadline (`ShutdownClock.begin`) is undone once the engine is
    disposed, so a context that runs a lifespan and goes on (a test, an embedding program)
    keeps no deadline that has passed."""
    async with AsyncExitStack() as stack:
        stack.enter_context(database_deadline_scope())
        engine = create_engine(url, deadlines=deadlines)
        stack.callback(engine.dispose)
        yield engine
