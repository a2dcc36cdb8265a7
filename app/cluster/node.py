"""One gateway among several on one PostgreSQL: which buses it reads, and the rest mirrored.

Every `lease_period_s` the lease loop checks its lease session (one query that also lists who
holds what), takes free buses up to a fair share (any free bus once it has stayed free for a
round) and, with `rebalance`, hands its surplus to gateways with fewer. Taking a bus: lock,
reload its units from the database, start its reader and its command delivery. Giving one up:
stop delivery, stop the reader, commit its live state, unlock. A failed or slow check fences
the gateway: it stops sending commands on every bus at once (another gateway may soon own
them), but goes on reading them and holding their rows for the writer, which keeps them (in
memory, then in its journal) until the database is back. Once a lease round succeeds again,
each bus read without its lease is locked again if it is still free, else (another gateway
took it) its reader stops; rows read twice meanwhile are stored once (natural keys). Units of
buses read elsewhere are a mirror fed by the fan-out (`app/cluster/fanout.py`) and reloaded
from the database when the listener (re)connects.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import time
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import psycopg

from eqgw.bus.config import BusConfig
from eqgw.cluster.fanout import COMMAND_KIND, FLEET_KIND, FanOut, RemoteEvent
from eqgw.cluster.leases import Holders, LeaseConnection
from eqgw.cluster.settings import ClusterSettings
from eqgw.describe import describe
from eqgw.ingest import events
from eqgw.ingest.faults import OFFLINE, Episode, FaultTracker
from eqgw.ingest.state import UnitState
from eqgw.jsontypes import as_float, as_int, as_object, as_str
from eqgw.store.engine import deadline_left, is_sqlite
from eqgw.supervisor import Supervisor, spawn
from eqgw.tasks import cancel_and_wait, heals

if TYPE_CHECKING:
    from eqgw.commands.service import CommandService
    from eqgw.ingest.service import FrameSource, IngestService

log = logging.getLogger(__name__)

_FROM_UNIT_SLOTS_EXCLUDED = ("control", "parameters", "request")


def cluster_enabled(settings: ClusterSettings, database_url: str) -> bool:
    """Leases and fan-out are for PostgreSQL; on SQLite one gateway owns every bus."""
    return settings.mode == "auto" and not is_sqlite(database_url)


class ClusterNode:
    """Owns this gateway's bus leases; starts and stops readers and delivery to match."""

    def __init__(
        self,
        settings: ClusterSettings,
        database_url: str,
        buses: list[BusConfig],
        ingest: IngestService,
        commands: CommandService,
        *,
        make_source: Callable[[BusConfig], FrameSource] | None = None,
        supervisor: Supervisor | None = None,
    ) -> None:
        self.settings = settings
        # Owns the loops when given (the gateway's: failures reported in /readyz and
        # /metrics, a fault that will not heal ends them or the process); else plain tasks.
        self.supervisor = supervisor
        self.buses = {b.name: b for b in buses}
        self.ingest = ingest
        self.commands = commands
        self.instance_id = settings.instance_id
        self.leases = LeaseConnection(
            database_url,
            settings.instance_id,
            keepalive=(
                settings.keepalive_idle_s,
                settings.keepalive_interval_s,
                settings.keepalive_count,
            ),
            ttl_s=settings.lease_ttl_s,
            statement_timeout_s=settings.lease_timeout_s,
        )
        self._make_source = make_source or _bus_reader
        self.owned: dict[str, float] = {}  # bus -> since (wall time)
        # Buses still read after a fence, without their lease and without command delivery.
        self.held: dict[str, float] = {}  # bus -> since (wall time)
        self._sources: dict[str, FrameSource] = {}
        self._last_open: dict[str, float] = {}  # bus -> monotonic time last seen open
        self.holders = Holders({}, [])
        self.fenced = 0
        self.takeovers = 0
        self.last_round: float | None = None
        # When (monotonic) the round that last confirmed the lease was sent: the server heard
        # from this gateway after that, so its lease cannot expire before confirmed + expiry.
        self.confirmed_at: float | None = None
        self._fences = 0  # fences so far: a round that a fence overtook is void
        self.last_fence_at: float | None = None  # wall time, for /readyz
        self.last_error: str | None = None
        self._free_before: set[str] = set()
        # bus -> monotonic time until which this gateway leaves it to others
        self._given_up: dict[str, float] = {}
        self._shed_buses: set[str] = set()  # handed to others by rebalancing
        # bus -> monotonic time until which rebalancing leaves it here: it was handed over
        # and nobody took it (the others cannot reach it), so moving it again would only
        # leave it unread, round after round.
        self._keep: dict[str, float] = {}
        self._task: asyncio.Task[None] | None = None
        self._resync_task: asyncio.Task[None] | None = None
        # Fleet changes (eqgw.fleet.sync) and lease rounds take turns; a change wakes the
        # lease loop, so a new bus is taken at once rather than at the next period.
        self._fleet_lock = asyncio.Lock()
        self._wake = asyncio.Event()
        # Buses taken out of the fleet: late fan-out news of them is dropped, not mirrored.
        self._removed: set[str] = set()
        # Called when another gateway announces a fleet change.
        self.on_fleet_change: Callable[[], None] | None = None
        self._clock_task: asyncio.Task[None] | None = None
        self.fanout: FanOut | None = None

    # -- lifecycle ----------------------------------------------------------------------------

    async def start(self) -> None:
        """Join: open the lease session, start the fan-out, take a first share of buses."""
        await self.leases.connect()
        self.fanout = FanOut(
            self.leases.conninfo,
            f"eqgw_{self.leases.namespace}",
            self.instance_id,
            self.ingest.hub,
            self.commands.hub,
            on_remote=self._on_remote,
            on_resync=self.resync_mirror,
            supervisor=self.supervisor,
        )
        await self.fanout.start()
        try:
            async with self._fleet_lock:
                await self._round()
        except (psycopg.Error, OSError, TimeoutError) as exc:  # the lease loop tries again
            self.last_error = describe(exc)
            await self._fence(self.last_error)
        self._task = spawn(self.supervisor, "cluster leases", self._loop)
        self._resync_task = spawn(self.supervisor, "cluster mirror", self._refresh_loop)
        self._clock_task = spawn(self.supervisor, "cluster fence clock", self._fence_clock)

    async def stop(self) -> None:
        """Leave: hand every bus over (state committed first), end the session, stop fan-out."""
        for task in (self._clock_task, self._task, self._resync_task):
            if task is not None:
                await cancel_and_wait(task)
        self._task = self._resync_task = self._clock_task = None
        buses = [*self.owned, *self.held]
        for bus in buses:  # first no command goes out, then every reader stops at once
            self.owned.pop(bus, None)
            self.held.pop(bus, None)
            self._sources.pop(bus, None)
            self.commands.remove_writer(bus)
        # The database away: nothing to wait for (the writer keeps the rows in its journal).
        away = self.ingest.writer.status().consecutive_failures > 0
        left = deadline_left()  # a shutdown's database deadline
        flush = 10.0 if left is None else min(10.0, left)
        with contextlib.suppress(Exception):
            await self.ingest.remove_sources(buses, flush_timeout=None if away else flush)
        with contextlib.suppress(Exception):
            await self.leases.close()
        if self.fanout is not None:
            await self.fanout.stop()

    def routable(self, bus: str) -> bool:
        """Whether some gateway delivers commands on `bus` (or this one will take it)."""
        return bus in self.owned or bus in self.holders.owners or bus in self.buses

    def status(self) -> dict[str, Any]:
        """Who owns what, for /readyz."""
        now = time.time()
        return {
            "instance": self.instance_id,
            "owned": sorted(self.owned),
            "owned_since": dict(sorted(self.owned.items())),
            "held": sorted(self.held),
            "owners": {b: self.holders.owners.get(b) for b in sorted(self.buses)},
            "instances": self.holders.instances,
            "lease_period_s": self.settings.lease_period_s,
            "takeover_bound_s": self.settings.takeover_bound_s,
            "lease_connected": self.leases.connected,
            "last_round_age_s": None if self.last_round is None else now - self.last_round,
            "last_error": self.last_error,
            "fenced": self.fenced,
            "last_fence_at": self.last_fence_at,
            "lease_age_s": None
            if self.confirmed_at is None
            else time.monotonic() - self.confirmed_at,
            "fence_after_s": self.settings.fence_after_s,
            "takeovers": self.takeovers,
            "fanout": self.fanout.status() if self.fanout else None,
        }

    # -- the lease loop -----------------------------------------------------------------------

    async def _loop(self) -> None:
        while True:
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout(self.settings.lease_period_s):
                    await self._wake.wait()
            self._wake.clear()
            try:
                if not self.leases.connected:
                    await self.leases.connect()
                async with self._fleet_lock:
                    await self._round()
            except (psycopg.Error, OSError, TimeoutError) as exc:
                self.last_error = describe(exc)
                await self._fence(self.last_error)
                if not heals(exc):
                    raise  # a refused login, a dropped database: its owner stops it
            except Exception as exc:
                await self._fence("lease round failed")
                if not heals(exc):
                    raise  # a bug: its owner says so once and reports it
                log.exception("cluster: lease round failed")

    async def _fence_clock(self) -> None:
        """Fence by this gateway's own clock, whatever the lease round is waiting for: once
        the lease was last confirmed `fence_after_s` ago, the server may soon free it for
        another gateway, so nothing more is sent on any bus."""
        s = self.settings
        tick = min(0.2, s.fence_margin_s / 4)
        while True:
            await asyncio.sleep(tick)
            confirmed = self.confirmed_at
            if not self.owned or confirmed is None:
                continue
            age = time.monotonic() - confirmed
            if age > s.fence_after_s:
                self.last_error = f"lease not confirmed for {age:.1f} s"
                await self._fence(self.last_error)

    async def _round(self) -> None:
        s = self.settings
        names = sorted(self.buses)
        fences = self._fences
        sent = time.monotonic()
        async with asyncio.timeout(s.lease_timeout_s):
            holders = await self.leases.holders(names)
        if self._fences != fences:
            # The clock fenced this gateway while the round waited: its answer is stale.
            raise TimeoutError("the lease round answered after the gateway fenced itself")
        self.confirmed_at = sent
        self.holders = holders
        self.last_round = time.time()
        self.last_error = None
        if self.held:
            await self._settle_held(holders)
        for bus in list(self.owned):
            if holders.owners.get(bus) != self.instance_id:
                # The server no longer shows our lock: never keep reading without it.
                await self._give_up(bus, unlock=False, flush_timeout=None)
        n_instances = max(1, len(holders.instances))
        share = math.ceil(len(names) / n_instances)
        free = [b for b in names if b not in holders.owners]
        now = time.monotonic()
        for bus in free:
            recently = now < self._given_up.get(bus, -math.inf)
            # A fair share first; beyond it, a bus nobody took for a whole round.
            if not recently and (len(self.owned) < share or bus in self._free_before):
                async with asyncio.timeout(s.lease_timeout_s):
                    got = await self.leases.try_acquire(bus)
                if got:
                    await self._take(bus)  # `holders` is self.holders: the owner shown too
                    if bus in self._shed_buses:
                        self._keep[bus] = now + max(30.0, 10 * s.lease_period_s)
        self._shed_buses -= set(holders.owners)
        self._free_before = {b for b in free if b not in self.owned}
        if n_instances > 1:
            await self._drop_unreachable()
        if s.rebalance and n_instances > 1:
            await self._shed(holders, share)

    async def _settle_held(self, holders: Holders) -> None:
        """After a fence: lock again each bus still read if nobody took it, else stop it."""
        timeout = self.settings.lease_timeout_s
        for bus in sorted(self.held):
            got = holders.owners.get(bus) == self.instance_id  # the session kept it
            if bus not in holders.owners:
                async with asyncio.timeout(timeout):
                    got = await self.leases.try_acquire(bus)
            self.held.pop(bus, None)
            if got:
                self.owned[bus] = time.time()
                holders.owners[bus] = self.instance_id
                self._add_delivery(bus)
                log.info("cluster: %s holds bus %s again", self.instance_id, bus)
            else:
                # Another gateway reads it now: what was read here meanwhile is committed
                # by this writer when it can (the same rows twice are stored once).
                self._sources.pop(bus, None)
                await self.ingest.remove_source(bus, flush_timeout=None)
                log.info(
                    "cluster: %s leaves bus %s to %s",
                    self.instance_id,
                    bus,
                    holders.owners.get(bus, "another gateway"),
                )

    def _add_delivery(self, bus: str) -> None:
        from eqgw.bus.reader import BusReader
        from eqgw.bus.writer import BusWriter

        src = self._sources.get(bus)
        if isinstance(src, BusReader):
            src.set_transmit(True)
            self.commands.add_writer(bus, BusWriter(src))

    async def _drop_unreachable(self) -> None:
        """Give a bus this gateway cannot open to the others: one of them may reach it."""
        s = self.settings
        now = time.monotonic()
        for bus, src in list(self._sources.items()):
            state = getattr(src.status(), "state", "open")
            if state == "open":
                self._last_open[bus] = now
            # Only after a failed open: a slow one (a loaded machine) is still trying.
            elif state == "backoff" and now - self._last_open.get(bus, now) > s.unreachable_s:
                log.warning("cluster: cannot open bus %s here; leaving it to others", bus)
                await self._give_up(bus, unlock=True, flush_timeout=5.0)
                self._given_up[bus] = now + max(s.unreachable_s, 6 * s.lease_period_s)

    async def _shed(self, holders: Holders, share: int) -> None:
        """Hand surplus buses to gateways below their share."""
        counts = dict.fromkeys(holders.instances, 0)
        for owner in holders.owners.values():
            counts[owner] = counts.get(owner, 0) + 1
        below = sum(max(0, share - c) for i, c in counts.items() if i != self.instance_id)
        surplus = min(len(self.owned) - share, below)
        now = time.monotonic()
        movable = [b for b in self.owned if self._keep.get(b, -math.inf) < now]
        for bus in sorted(movable, key=self.owned.__getitem__, reverse=True)[: max(0, surplus)]:
            await self._give_up(bus, unlock=True, flush_timeout=5.0)
            self._given_up[bus] = now + 3 * self.settings.lease_period_s
            self._shed_buses.add(bus)

    async def _take(self, bus: str) -> None:
        cfg = self.buses[bus]
        src = self._make_source(cfg)
        # Owned and shown with this gateway as its owner together (/readyz at any moment):
        # the lock is held from here, while the reader starts.
        self.owned[bus] = time.time()
        self.holders.owners[bus] = self.instance_id
        self._sources[bus] = src
        self._last_open[bus] = time.monotonic()
        self.takeovers += 1
        try:
            await self.ingest.add_source(src)
        except Exception:
            self.owned.pop(bus, None)
            self._sources.pop(bus, None)
            if self.holders.owners.get(bus) == self.instance_id:
                del self.holders.owners[bus]
            with contextlib.suppress(Exception):
                await self.leases.release(bus)
            raise
        self._add_delivery(bus)
        log.info("cluster: %s reads bus %s", self.instance_id, bus)

    async def _give_up(self, bus: str, *, unlock: bool, flush_timeout: float | None) -> None:
        self.owned.pop(bus, None)
        self._sources.pop(bus, None)
        if self.holders.owners.get(bus) == self.instance_id:
            del self.holders.owners[bus]
        self.commands.remove_writer(bus)
        try:
            await self.ingest.remove_source(bus, flush_timeout=flush_timeout)
        finally:
            if unlock and self.leases.connected:
                with contextlib.suppress(psycopg.Error, OSError):
                    await self.leases.release(bus)
        log.info("cluster: %s no longer reads bus %s", self.instance_id, bus)

    def _stop_transmitting(self, bus: str) -> None:
        """No frame at all from this gateway on a bus it holds no lease on (its address claim
        and its answers to other nodes included): another gateway may hold it now."""
        from eqgw.bus.reader import BusReader

        src = self._sources.get(bus)
        if isinstance(src, BusReader):
            src.set_transmit(False)

    async def _fence(self, why: str) -> None:
        """The lease session failed or hung: stop sending commands everywhere at once; the
        buses are still read (their rows held), without a lease, until a round succeeds."""
        self._fences += 1
        if self.owned:
            log.warning(
                "cluster: fencing (%s): no command delivery on %d buses; still reading them",
                why,
                len(self.owned),
            )
            self.fenced += 1
            self.last_fence_at = time.time()
        now = time.time()
        for bus in list(self.owned):
            self.owned.pop(bus, None)
            self.held[bus] = now
            self.holders.owners.pop(bus, None)
            self.commands.remove_writer(bus)
            self._stop_transmitting(bus)
        conn_close = asyncio.create_task(self.leases.close())
        with contextlib.suppress(Exception, TimeoutError):
            async with asyncio.timeout(1.0):
                await conn_close
        self.holders = Holders({}, [])

    # -- fleet changes (eqgw.fleet.sync) -----------------------------------------------------

    async def remove_buses(self, names: list[str]) -> None:
        """Buses taken out of the fleet (or changed: they come back by `add_buses`): a bus
        read here stops and its lease is given up (its state committed first)."""
        async with self._fleet_lock:
            for bus in names:
                if bus in self.owned:
                    await self._give_up(bus, unlock=True, flush_timeout=5.0)
                if bus in self.held:  # read after a fence, without its lease
                    self.held.pop(bus, None)
                    self._sources.pop(bus, None)
                    self.commands.remove_writer(bus)
                    await self.ingest.remove_source(bus, flush_timeout=5.0)
                self.buses.pop(bus, None)
                self.holders.owners.pop(bus, None)
                self._free_before.discard(bus)
                self._shed_buses.discard(bus)
                self._given_up.pop(bus, None)
                self._keep.pop(bus, None)
                self._last_open.pop(bus, None)
                self._removed.add(bus)

    async def add_buses(self, buses: list[BusConfig]) -> None:
        """Buses added to the fleet (or changed): the next lease round, at once, takes each
        that is free, here or on another gateway (exactly one holds its lease)."""
        async with self._fleet_lock:
            for cfg in buses:
                self.buses[cfg.name] = cfg
                self._removed.discard(cfg.name)
        self._wake.set()

    # -- the mirror of other gateways' units --------------------------------------------------

    async def _refresh_loop(self) -> None:
        while True:
            await asyncio.sleep(self.settings.mirror_refresh_s)
            try:
                await self.resync_mirror()
            except Exception as exc:  # the database may be away
                if not heals(exc):
                    raise  # its owner stops it (a fatal one: the process)
                log.warning("cluster: mirror refresh failed: %s", exc)

    async def resync_mirror(self) -> None:
        """Reload the units of the configured buses this gateway does not read."""
        others = [b for b in self.buses if b not in self.owned and b not in self.held]
        if not others:
            return
        rows = await asyncio.to_thread(self.ingest._restart_rows, others)
        pipeline = self.ingest.pipeline
        for bus in others:
            if bus in self.owned or bus in self.held or bus in self.ingest.reading():
                continue  # taken while the query ran: the reader's state wins
            pipeline.reset_bus(bus)
            pipeline.restore([r for r in rows if r["bus"] == bus])

    def _on_remote(self, ev: RemoteEvent) -> bool:
        """Apply another gateway's event to the mirror; False to drop it (our own bus)."""
        if ev.kind == FLEET_KIND:
            if self.on_fleet_change is not None:
                self.on_fleet_change()
            return False
        if ev.kind == COMMAND_KIND:
            if ev.unit.bus in self.owned:
                self.commands.poke()  # queued elsewhere for a bus we deliver on
            return True
        if ev.unit.bus in self._removed:
            return False  # late news of a bus no longer in the fleet
        if ev.unit.bus in self.owned or ev.unit.bus in self.held:
            return False  # late news from a previous owner: our reader is the truth now
        live = self.ingest.live
        st = live.get(ev.unit.bus, ev.unit.sa)
        if st is None:
            m = self.ingest.settings.monitor
            st = UnitState(
                ref=ev.unit,
                faults=FaultTracker(
                    offline_after_s=m.offline_after_s,
                    dm1_stale_after_s=m.dm1_stale_after_s,
                    heartbeat_stuck_after=m.heartbeat_stuck_after,
                ),
            )
            live.units[ev.unit.key] = st
        _apply(st, ev)
        return True


def _apply(st: UnitState, ev: RemoteEvent) -> None:
    data = ev.data
    if ev.kind == events.LIVE:
        slot, fields = data.get("slot"), as_object(data.get("fields")) or {}
        if not isinstance(slot, str):
            return
        st.latest[slot] = (ev.ts, fields)
        if not slot.startswith(_FROM_UNIT_SLOTS_EXCLUDED):
            _seen(st, ev.ts)
        if slot == "status":
            st.status_flags = fields
        elif slot == "dm1":
            st.dm1 = (fields.get("lamps"), fields.get("dtcs"))
        elif slot in ("component_id", "software_id"):
            if slot == "component_id":
                st.model = as_str(fields.get("text"))
            else:
                st.software_id = as_str(fields.get("text"))
            if fields.get("series"):
                st.series = as_int(fields["series"])
    elif ev.kind == events.STATUS_CHANGE:
        st.status_flags = as_object(data.get("flags"))
        _seen(st, ev.ts)
    elif ev.kind == events.UNIT_ONLINE:
        _seen(st, ev.ts)
        st.faults.open.pop(OFFLINE, None)
    elif ev.kind == events.UNIT_PARKED:
        since = data.get("parked_since")
        if isinstance(since, int | float) and not (st.last_seen and st.last_seen > since):
            st.faults.parked_since = float(since)
    elif ev.kind == events.FAULT_CLOSE:
        st.faults.open.pop(str(data.get("fault")), None)
    elif ev.kind in (events.FAULT_OPEN, events.FAULT_UPDATE, events.FAULT_STALE):
        fault = str(data.get("fault"))
        st.faults.open[fault] = Episode(
            fault=fault,
            started_at=_number(data.get("started_at", ev.ts), ev.ts),
            last_seen_at=_number(data.get("last_seen_at", ev.ts), ev.ts),
            sources=set(str(data.get("source") or "").split("+")) - {""},
            state=as_str(data.get("state", "active")) or "active",
            occurrence_count=as_int(data.get("occurrence_count")),
            spn=as_int(data.get("spn")),
            fmi=as_int(data.get("fmi")),
        )


def _number(value: object, default: float) -> float:
    """A time of another gateway's event (`default` when it is not a number)."""
    number = as_float(value)
    return default if number is None else number


def _seen(st: UnitState, ts: float) -> None:
    if st.first_seen is None or ts < st.first_seen:
        st.first_seen = ts
    if st.last_seen is None or ts > st.last_seen:
        st.last_seen = ts
    if OFFLINE in st.faults.open and ts > st.faults.open[OFFLINE].started_at:
        st.faults.open.pop(OFFLINE, None)
    parked = st.faults.parked_since
    if parked is not None and ts > parked:
        st.faults.parked_since = None


def _bus_reader(cfg: BusConfig) -> FrameSource:
    from eqgw.bus.reader import BusReader

    return BusReader(cfg)
