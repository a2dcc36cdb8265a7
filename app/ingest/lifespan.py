"""The ingest of a running gateway, as a part of the lifespan (see app/main.py)."""

from __future__ import annotations

from collections.abc import AsyncIterator, Callable, Sequence
from contextlib import asynccontextmanager
from typing import TYPE_CHECKING

from eqgw.ingest.service import FrameSource, IngestService

if TYPE_CHECKING:
    from sqlalchemy import Engine

    from eqgw.config import Settings
    from eqgw.store.lifespan import ShutdownClock
    from eqgw.supervisor import Supervisor


@asynccontextmanager
async def ingesting(
    settings: Settings,
    engine: Engine,
    sources: Sequence[FrameSource],
    tasks: Supervisor,
    *,
    paused: bool,
    shutdown: ShutdownClock,
    on_stopped: Callable[[int], None] | None = None,
) -> AsyncIterator[IngestService]:
    """Frames of `sources` decoded, tracked and written (every bus `paused` until a cluster
    lease says otherwise); its loops under `tasks`. At the end its final flush gets what is
    left of the shutdown's time (`shutdown.left()`, at least 1 s), and `on_stopped` the rows it
    could not write."""
    ingest = IngestService(
        settings,
        engine=engine,
        sources=list(sources),
        supervisor=tasks,
        fleet_from_settings=False,
    )
    if paused:
        ingest.pause_all()
    await ingest.start(migrate=False)
    try:
        yield ingest
    finally:
        left = await ingest.stop(timeout=max(1.0, shutdown.left()))
        if on_stopped is not None:
            on_stopped(left)
