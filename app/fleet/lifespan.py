"""The fleet of a running gateway, as parts of the lifespan (see app/main.py): seeded from
the fleet file into a database that has none, then followed as it changes."""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import AsyncIterator, Callable
from contextlib import asynccontextmanager
from dataclasses import dataclass
from typing import TYPE_CHECKING

from eqgw.fleet import registry
from eqgw.fleet.sync import DepotMap, FleetSync, FleetView

if TYPE_CHECKING:
    from sqlalchemy import Engine

    from eqgw.cluster.node import ClusterNode
    from eqgw.commands.service import CommandService
    from eqgw.config import Settings
    from eqgw.ingest.service import IngestService
    from eqgw.supervisor import Supervisor

log = logging.getLogger(__name__)


@dataclass(slots=True)
class Fleet:
    """The fleet this gateway starts with: what it runs (`view`), its version, the depots."""

    view: FleetView
    version: int
    depots: DepotMap


async def seeded_fleet(engine: Engine, settings: Settings, fleet_file: Settings) -> Fleet:
    """The database's fleet (the fleet file seeds a database that has none), put into
    `settings` (its vehicles and buses, with those of its own that `fleet_file` lacks: a
    simulated fleet's)."""
    view = FleetView(
        settings,
        [v for v in settings.vehicles if fleet_file.vehicle(v.id) is None],
        settings.buses[len(fleet_file.buses) :],
    )
    seeded = await asyncio.to_thread(
        registry.seed, engine, fleet_file.vehicles, fleet_file.buses, fleet_file.address_claim
    )
    _say_seeded(seeded)
    settings.vehicles, settings.buses = view.compose(seeded.fleet)
    return Fleet(view, seeded.fleet.version, DepotMap(registry.depots_of(settings.vehicles)))


@asynccontextmanager
async def following(
    engine: Engine,
    fleet: Fleet,
    ingest: IngestService,
    commands: CommandService,
    node: ClusterNode | None,
    tasks: Supervisor,
    *,
    on_change: Callable[[], None],
) -> AsyncIterator[FleetSync]:
    """The fleet followed as it changes in the database (the `fleet sync` loop, supervised)."""
    sync = FleetSync(
        engine,
        fleet.view,
        version=fleet.version,
        ingest=ingest,
        commands=commands,
        depots=fleet.depots,
        node=node,
        on_change=on_change,
    )
    async with tasks.running("fleet sync", sync.run):
        yield sync


def _say_seeded(seeded: registry.SeedResult) -> None:
    """One line on what the fleet file did at this start."""
    fleet = seeded.fleet
    if seeded.seeded:
        log.info(
            "fleet: the database had no fleet: seeded from the fleet file (%d vehicles, %d "
            "buses); from now on the database holds the fleet",
            len(fleet.vehicles),
            len(fleet.buses),
        )
    elif seeded.differ:
        when = (
            time.strftime("%Y-%m-%d %H:%M", time.localtime(seeded.seeded_at))
            if seeded.seeded_at
            else "?"
        )
        shown = ", ".join(seeded.differ[:5]) + (", ..." if len(seeded.differ) > 5 else "")
        log.warning(
            "fleet: the fleet file's vehicles and buses were not applied: the database holds "
            "the fleet (since %s, from %s; version %d) and %d of the file's differ from it "
            "(%s). Manage vehicles with the API (/api/v1/vehicles) or `eqgw vehicles import`; "
            "remove [[vehicles]] and [[buses]] from the file to silence this",
            when,
            seeded.seeded_from,
            fleet.version,
            len(seeded.differ),
            shown,
        )
