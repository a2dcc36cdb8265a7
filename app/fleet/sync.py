"""A running gateway follows the fleet in the database: buses opened, leased and closed.

Every `fleet.poll_s` (1 s) the gateway reads the fleet's version, one small query; when it has
moved, it loads the fleet and applies the difference. A change made through this gateway's API
is applied at once, and on PostgreSQL the other gateways are told through the fan-out's
LISTEN/NOTIFY (sealed like every other payload), so they apply it at once too; the poll is what
catches a change while a listener was away, and the only path on SQLite (where one gateway
reads every bus) and for `eqgw vehicles import`.

Applying: buses taken out of the fleet or changed stop first (their reader, their command
delivery; on PostgreSQL the lease is given up), their units leave the live view; then the
vehicles, their depots (key scopes) and the settings' lists are replaced; then new and changed
buses start: read here at once on one gateway, or left to the next lease round of every
gateway on PostgreSQL (exactly one gets the lease). A bus that fails to start is retried at
the next poll.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from collections.abc import Callable, ItemsView, Iterator, Mapping, Sequence
from typing import TYPE_CHECKING, Any

from eqgw.bus.config import BusConfig
from eqgw.cluster.fanout import FLEET_KIND
from eqgw.config import Settings, VehicleConfig
from eqgw.describe import describe
from eqgw.fleet import registry
from eqgw.ingest.pipeline import BusBinding
from eqgw.store.engine import health_of
from eqgw.store.writes import VehicleInfo
from eqgw.tasks import heals

if TYPE_CHECKING:
    from sqlalchemy import Engine

    from eqgw.cluster.node import ClusterNode
    from eqgw.commands.service import CommandService
    from eqgw.ingest.service import IngestService

log = logging.getLogger(__name__)

# How long an API change waits for this gateway to apply it before answering.
APPLY_WAIT_S = 3.0


class DepotMap(Mapping[str, str | None]):
    """Each vehicle's depot, for key scopes by depot (eqgw.security.keys.Scope); replaced whole when
    the fleet changes, so a reader in another thread iterates a dict nobody changes."""

    def __init__(self, depots: Mapping[str, str | None] | None = None) -> None:
        self._map: dict[str, str | None] = dict(depots or {})

    def replace(self, depots: Mapping[str, str | None]) -> None:
        self._map = dict(depots)

    def __getitem__(self, key: str) -> str | None:
        return self._map[key]

    def get(self, key: str, default: Any = None) -> Any:
        return self._map.get(key, default)

    def __iter__(self) -> Iterator[str]:
        return iter(self._map)

    def __len__(self) -> int:
        return len(self._map)

    def items(self) -> ItemsView[str, str | None]:
        return self._map.items()


class FleetView:
    """The fleet a gateway runs: the database's, plus buses and vehicles of its own that are
    not the database's (a simulated fleet is private to its process)."""

    def __init__(
        self,
        settings: Settings,
        extra_vehicles: Sequence[VehicleConfig] = (),
        extra_buses: Sequence[BusConfig] = (),
    ) -> None:
        self.settings = settings
        self.extra_vehicles = list(extra_vehicles)
        self.extra_buses = list(extra_buses)

    def compose(self, fleet: registry.Fleet) -> tuple[list[VehicleConfig], list[BusConfig]]:
        """The vehicles and buses (each with the NAME it claims its address with) to run."""
        vehicles = list(fleet.vehicles.values())
        vehicles += [v for v in self.extra_vehicles if v.id not in fleet.vehicles]
        buses = [self.settings.apply_address_claim(b.model_copy()) for b in fleet.buses.values()]
        buses += [b for b in self.extra_buses if b.name not in fleet.buses]
        return vehicles, buses


def vehicle_info(vehicles: Sequence[VehicleConfig]) -> dict[str, VehicleInfo]:
    """The pipeline's record of each vehicle (written with its first unit)."""
    return {v.id: {"id": v.id, "name": v.display_name, "depot": v.depot} for v in vehicles}


class FleetSync:
    """Keeps a running gateway's buses, vehicles and depots as the database's fleet has them."""

    def __init__(
        self,
        engine: Engine,
        view: FleetView,
        *,
        version: int,
        ingest: IngestService,
        commands: CommandService,
        depots: DepotMap,
        node: ClusterNode | None = None,
        on_change: Callable[[], None] | None = None,
    ) -> None:
        self.engine = engine
        self.view = view
        self.settings = view.settings
        self.version = version
        self.ingest = ingest
        self.commands = commands
        self.depots = depots
        self.node = node
        self.on_change = on_change
        self.poll_s = self.settings.fleet.poll_s
        self.applied_at: float | None = None
        self.changes = 0
        self.last_error: str | None = None
        self.last_apply_s: float | None = None
        self.failures = 0  # polls failed in a row
        self._buses: dict[str, BusConfig] = {b.name: b for b in self.settings.buses}
        self._failed: set[str] = set()  # buses that did not start: retried at the next poll
        self._wake = asyncio.Event()
        self._applied = asyncio.Condition()
        if node is not None:
            node.on_fleet_change = self.poke

    def poke(self) -> None:
        """Read the fleet now (a change was made here or announced by another gateway)."""
        self._wake.set()

    async def changed(self, version: int) -> None:
        """A change made through this gateway: the other gateways are told, this one applies
        it, and the caller waits (a moment at most) until it has."""
        self.poke()
        fanout = self.node.fanout if self.node is not None else None
        if fanout is not None:
            try:
                await fanout.announce(FLEET_KIND, {"version": version})
            except Exception as exc:  # they poll too: late by a poll at most
                log.warning(
                    "fleet: change %d not announced to the other gateways: %s",
                    version,
                    describe(exc),
                )
        with contextlib.suppress(TimeoutError):
            async with asyncio.timeout(APPLY_WAIT_S), self._applied:
                await self._applied.wait_for(lambda: self.version >= version)

    async def run(self) -> None:
        """The loop (supervised): read the version every poll, or when poked; apply a change."""
        while True:
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout(self.poll_s):
                    await self._wake.wait()
            self._wake.clear()
            if health_of(self.engine).down():
                continue  # it failed moments ago (here or elsewhere): not asked again yet
            try:
                await self.sync()
            except Exception as exc:  # the database may be away: the next poll tries again
                if not heals(exc):
                    raise  # its supervisor stops it (a fatal one: the process)
                self.last_error = describe(exc)
                self.failures += 1
                # Said when it starts failing and now and then while it lasts, not every poll.
                if self.failures == 1 or self.failures % 60 == 0:
                    log.warning(
                        "fleet: cannot read the fleet (%d in a row): %s",
                        self.failures,
                        self.last_error,
                    )
            else:
                if self.failures:
                    log.info("fleet: the fleet is read again (after %d failures)", self.failures)
                self.failures = 0

    async def sync(self) -> bool:
        """Apply the database's fleet if it moved (or a bus is still to start); whether it
        did."""
        current = await asyncio.to_thread(registry.fleet_version, self.engine)
        if current == self.version and not self._failed:
            return False
        fleet = await asyncio.to_thread(registry.load_fleet, self.engine)
        await self.apply(fleet)
        return True

    async def apply(self, fleet: registry.Fleet) -> None:
        """Make this gateway run `fleet`."""
        started = time.monotonic()
        vehicles, buses = self.view.compose(fleet)
        wanted = {b.name: b for b in buses}
        old = self._buses
        stop = [n for n, b in old.items() if n not in wanted or bus_key(b) != bus_key(wanted[n])]
        start = [n for n in wanted if n not in old or n in stop or n in self._failed]
        self._failed.clear()
        pipeline = self.ingest.pipeline
        if stop:
            await self._stop(stop)
        for name in stop:
            pipeline.remove_binding(name)
            self.commands.buses.pop(name, None)
            old.pop(name, None)
        # Vehicles, depots and the settings' lists at once (each replaced whole).
        self.settings.vehicles = vehicles
        self.settings.buses = buses
        self.depots.replace(registry.depots_of(vehicles))
        pipeline.vehicles = vehicle_info(vehicles)
        for name in start:
            cfg = wanted[name]
            if name not in pipeline.bindings:
                pipeline.add_binding(
                    BusBinding(
                        cfg.name, cfg.vehicle_id, tuple(cfg.equalizer_sas), cfg.request_byte_order
                    )
                )
            self.commands.buses[name] = cfg
        started_ok = await self._start([wanted[n] for n in start])
        for name in started_ok:
            old[name] = wanted[name]
        for invalid in fleet.invalid:
            log.error("fleet: %s; not used", invalid)
        if stop or start:
            log.info(
                "fleet version %d: %d buses stopped, %d started%s",
                fleet.version,
                len(stop),
                len(started_ok),
                f", {len(self._failed)} failed" if self._failed else "",
            )
        async with self._applied:
            self.version = fleet.version
            self._applied.notify_all()
        self.applied_at = time.time()
        self.last_apply_s = time.monotonic() - started
        self.last_error = None
        self.changes += 1
        if self.on_change is not None:
            self.on_change()

    async def _stop(self, names: list[str]) -> None:
        if self.node is not None:
            await self.node.remove_buses(names)
            return
        for name in names:
            self.commands.remove_writer(name)
        if names:
            await self.ingest.remove_sources(names, flush_timeout=5.0)

    async def _start(self, cfgs: list[BusConfig]) -> list[str]:
        if self.node is not None:
            await self.node.add_buses(cfgs)
            return [c.name for c in cfgs]
        from eqgw.bus.reader import BusReader
        from eqgw.bus.writer import BusWriter

        done = []
        for cfg in cfgs:
            src = BusReader(cfg)
            try:
                await self.ingest.add_source(src)
            except Exception as exc:
                self._failed.add(cfg.name)
                self.last_error = f"bus {cfg.name}: {describe(exc)}"
                log.error("fleet: bus %s not started: %s", cfg.name, describe(exc))
                continue
            self.commands.add_writer(cfg.name, BusWriter(src))
            done.append(cfg.name)
        return done

    def status(self) -> dict[str, Any]:
        """The fleet this gateway runs, for /readyz."""
        return {
            "version": self.version,
            "applied_at": self.applied_at,
            "vehicles": len(self.settings.vehicles),
            "buses": len(self.settings.buses),
            "poll_s": self.poll_s,
            "changes": self.changes,
            "last_apply_s": self.last_apply_s,
            "last_error": self.last_error,
            "failures": self.failures,
        }


def bus_key(bus: BusConfig) -> dict[str, Any]:
    """What makes two running buses the same (every field, the derived NAME included)."""
    return bus.model_dump()
