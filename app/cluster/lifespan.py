"""The cluster's parts of a running gateway's lifespan (see app/main.py): the startup lock,
and the node that shares the buses with the other gateways of one PostgreSQL."""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from typing import TYPE_CHECKING

from eqgw.cluster.leases import StartupLock

if TYPE_CHECKING:
    from sqlalchemy import Engine

    from eqgw.bus.config import BusConfig
    from eqgw.cluster.node import ClusterNode
    from eqgw.cluster.settings import ClusterSettings
    from eqgw.commands.service import CommandService
    from eqgw.ingest.service import IngestService
    from eqgw.supervisor import Supervisor


class Starting:
    """Held while this gateway starts (gateways starting together on one PostgreSQL start
    one at a time); `release()` once it has, else at the end of the block."""

    def __init__(self, lock: StartupLock) -> None:
        self._lock = lock

    async def release(self) -> None:
        await asyncio.to_thread(self._lock.release)


@asynccontextmanager
async def startup_lock(engine: Engine) -> AsyncIterator[Starting]:
    lock = StartupLock(engine)
    await asyncio.to_thread(lock.acquire)
    try:
        yield Starting(lock)
    finally:
        lock.release()


@asynccontextmanager
async def cluster_node(
    enabled: bool,
    settings: ClusterSettings,
    buses: list[BusConfig],
    ingest: IngestService,
    commands: CommandService,
    tasks: Supervisor,
) -> AsyncIterator[ClusterNode | None]:
    """The node when `enabled` (its loops under `tasks`): it reads only the buses it holds a
    lease on; None otherwise. Stopped (every bus handed over) at the end."""
    if not enabled:
        yield None
        return
    from eqgw.cluster.node import ClusterNode

    url = ingest.settings.database_url
    node = ClusterNode(settings, url, buses, ingest, commands, supervisor=tasks)
    await node.start()
    try:
        yield node
    finally:
        await node.stop()
