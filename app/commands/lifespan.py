"""Command delivery and unit identification of a running gateway, as a part of the lifespan
(see app/main.py)."""

from __future__ import annotations

from collections.abc import AsyncIterator, Callable, Sequence
from contextlib import asynccontextmanager
from typing import TYPE_CHECKING

from eqgw.bus.writer import BusWriter
from eqgw.commands.identify import UnitIdentifier
from eqgw.commands.service import CommandService

if TYPE_CHECKING:
    from sqlalchemy import Engine

    from eqgw.bus.reader import BusReader
    from eqgw.config import Settings
    from eqgw.ingest.service import IngestService
    from eqgw.supervisor import Supervisor
    from eqgw.web.settings import ApiSettings


@asynccontextmanager
async def commanding(
    settings: Settings,
    api: ApiSettings,
    engine: Engine,
    ingest: IngestService,
    readers: Sequence[BusReader],
    tasks: Supervisor,
    *,
    routable: Callable[[str], bool],
) -> AsyncIterator[CommandService]:
    """Queued commands delivered on the buses of `readers` (`routable(bus)`: whether some
    gateway of the cluster delivers on a bus this one does not read), and the units without
    a series asked who they are. At the end: the command hub closed, then both stopped."""
    service = CommandService(
        engine,
        ingest.live,
        {r.name: BusWriter(r) for r in readers},
        {b.name: b for b in settings.buses},
        lambda: {v.id for v in settings.vehicles},
        api,
        routable=routable,
        supervisor=tasks,
    )
    await service.start()
    try:
        identifier = UnitIdentifier(ingest.hub, service, supervisor=tasks)
        await identifier.start()
        try:
            yield service
        finally:
            service.hub.close()
            await identifier.stop()
    finally:
        await service.stop()
