"""The command queue: refuse what cannot be sent, queue the rest as rows, deliver and confirm.

Nothing stale (a command past its expiry is never sent), nothing unauthorized (the API checks
roles before calling in), nothing silent (every command ends in a final state with a reason).
Control and parameter messages repeat at the manuals' 1 s until the status flags confirm a control
command, or a fixed number of sends for parameter writes (which have no read-back).
"""

from __future__ import annotations

import asyncio
import dataclasses
import logging
import time
import uuid
from collections import Counter
from collections.abc import Awaitable, Callable, Mapping
from datetime import UTC, datetime
from typing import NamedTuple

from sqlalchemy import Connection, Engine

from eqgw.bus.config import BusConfig
from eqgw.bus.writer import BusWriter
from eqgw.commands import lifecycle as life
from eqgw.commands import repository as q
from eqgw.commands.delivery import Delivery, _Tracking
from eqgw.commands.model import Command, CommandKind, CommandPayload, CommandState, Json
from eqgw.commands.validation import (
    CommandRefused,
    Submitter,
    _replayed,
    affected_units,
    conflict,
    control_payload,
    parameter_payload,
    request_payload,
    targets,
)
from eqgw.ingest.hub import EventHub
from eqgw.ingest.state import LiveState, UnitState
from eqgw.supervisor import Supervisor, spawn
from eqgw.tasks import STOP_TIMEOUT_S, cancel_and_wait
from eqgw.web.settings import ApiSettings

log = logging.getLogger(__name__)


class _Addressed(NamedTuple):
    """What a command reaches: the unit it is filed under, every unit it reaches by SA (None:
    configured, never heard), its checked payload and how many times it may be sent."""

    unit: UnitState
    on_bus: list[tuple[int, UnitState | None]]
    payload: CommandPayload
    max_sends: int


class CommandService(Delivery):
    """Validates and queues commands, and delivers those for the buses this process owns."""

    def __init__(
        self,
        engine: Engine,
        live: LiveState,
        writers: Mapping[str, BusWriter],
        buses: Mapping[str, BusConfig],
        vehicles: Callable[[], set[str]],
        settings: ApiSettings,
        hub: EventHub | None = None,
        routable: Callable[[str], bool] | None = None,
        supervisor: Supervisor | None = None,
    ) -> None:
        self.engine = engine
        # The gateway's: a delivery failure that will not heal (a bug, storage gone for
        # good) stops delivery, reported failed (a fatal one ends the process).
        self.supervisor = supervisor
        self._serial_engine = engine.execution_options(sqlite_begin="IMMEDIATE")
        self.live = live
        self.writers = dict(writers)
        self.buses = dict(buses)
        self._vehicles = vehicles
        # With several gateways on one database: whether some gateway (maybe another one)
        # delivers on a bus this one does not own; commands for it are queued, not refused.
        self._routable = routable
        self.settings = settings
        self.hub = hub or EventHub(settings.ws_queue)
        self.outcomes: Counter[tuple[str, str]] = Counter()
        self.frames_sent = 0
        self._pending: dict[str, Command] = {}
        self._submitting: set[str] = set()  # ids inserted by submit() but not yet queued
        self._tracking: dict[str, _Tracking] = {}
        self._wake = asyncio.Event()
        self._reload_now = False
        self._submit_lock = asyncio.Lock()
        self._task: asyncio.Task[None] | None = None

    # -- lifecycle ----------------------------------------------------------------------------

    async def start(self) -> None:
        """Load commands left pending by a previous run and start delivering."""
        await self._reload()
        self._task = spawn(self.supervisor, "command delivery", self._run)

    async def stop(self, timeout: float = STOP_TIMEOUT_S) -> None:
        """Cancel delivery and wait for it to end, at most `timeout` seconds."""
        task, self._task = self._task, None
        if task is not None:
            await cancel_and_wait(task, timeout)

    # -- buses taken and given up at run time ---------------------------------------------

    def add_writer(self, bus: str, writer: BusWriter) -> None:
        """Deliver on `bus` from now on, starting with what is queued for it."""
        self.writers[bus] = writer
        self.poke()

    def remove_writer(self, bus: str) -> None:
        """Stop delivering on `bus` at once; its pending commands stay queued in the
        database for the gateway that takes the bus over."""
        self.writers.pop(bus, None)
        for cid in [cid for cid, cmd in self._pending.items() if cmd.bus == bus]:
            self._pending.pop(cid, None)
            self._tracking.pop(cid, None)

    def poke(self) -> None:
        """Look for commands queued elsewhere now instead of at the next periodic reload."""
        self._reload_now = True
        self._wake.set()

    def delivers(self, bus: str) -> bool:
        """Whether this process transmits on `bus` now."""
        return bus in self.writers

    # -- submission ---------------------------------------------------------------------------

    def _unit(self, vehicle_id: str, sa: int | None) -> UnitState:
        units = self.live.of_vehicle(vehicle_id)
        if vehicle_id not in self._vehicles() and not units:
            raise CommandRefused(404, "unknown_vehicle", f"no vehicle {vehicle_id!r}")
        if sa is None:
            if len(units) == 1:
                return units[0]
            if not units:
                raise CommandRefused(
                    409, "unit_offline", f"no unit of {vehicle_id} has been heard from yet"
                )
            sas = ", ".join(str(u.ref.sa) for u in units)
            raise CommandRefused(
                422, "unit_required", f"{vehicle_id} has several units ({sas}): give `unit`"
            )
        for u in units:
            if u.ref.sa == sa:
                return u
        raise CommandRefused(404, "unknown_unit", f"{vehicle_id} has no unit at SA {sa}")

    def _bus_units(
        self, vehicle_id: str, body: Mapping[str, Json]
    ) -> tuple[UnitState, list[tuple[int, UnitState | None]]]:
        """For a broadcast (control, parameters): the unit the record is filed under and every
        unit known on its bus, heard or configured, by SA (None: configured, never heard).

        Refused unless the request says it knows, `all_units`, when the bus has several."""
        sa = _sa(body.get("unit"))
        units = self.live.of_vehicle(vehicle_id)
        if sa is not None:
            st = self._unit(vehicle_id, sa)
        else:
            if vehicle_id not in self._vehicles() and not units:
                raise CommandRefused(404, "unknown_vehicle", f"no vehicle {vehicle_id!r}")
            if not units:
                raise CommandRefused(
                    409, "unit_offline", f"no unit of {vehicle_id} has been heard from yet"
                )
            buses = sorted({u.ref.bus for u in units})
            if len(buses) > 1:
                raise CommandRefused(
                    422,
                    "unit_required",
                    f"{vehicle_id} has units on several buses ({', '.join(buses)}): give "
                    "`unit`, any unit of the bus to write to",
                )
            st = min(units, key=lambda u: u.ref.sa)
        bus = st.ref.bus
        known: dict[int, UnitState | None] = {u.ref.sa: u for u in units if u.ref.bus == bus}
        cfg = self.buses.get(bus)
        for configured in cfg.equalizer_sas if cfg is not None else ():
            known.setdefault(configured, self.live.get(bus, configured))
        on_bus = sorted(known.items())
        self._check_path(bus)
        if len(on_bus) > 1 and body.get("all_units") is not True:
            sas = ", ".join(str(x) for x, _ in on_bus)
            named = f" (not only unit {sa})" if sa is not None else ""
            raise CommandRefused(
                422,
                "all_units_required",
                f"this write reaches every equalizer on bus {bus} (units {sas}){named}: "
                'send `"all_units": true` to write to all of them',
                affected_units=affected_units(on_bus),
            )
        return st, on_bus

    def _check_online(
        self, st: UnitState, on_bus: list[tuple[int, UnitState | None]] | None = None
    ) -> None:
        """Refuse unless every unit the command reaches is online and a gateway transmits."""
        reached = on_bus or [(st.ref.sa, st)]
        offline = [sa for sa, u in reached if u is None or not u.is_present()]
        parked = [u for _, u in reached if u is not None and u.faults.parked_since is not None]
        if parked and len(parked) == len(offline):
            since = max(u.faults.parked_since or 0.0 for u in parked)
            when = datetime.fromtimestamp(since, UTC).strftime("%Y-%m-%d %H:%M:%S UTC")
            raise CommandRefused(
                409,
                "unit_offline",
                f"{st.ref.vehicle_id} is parked: its bus has been silent since {when}, "
                "nothing would hear the command",
            )
        if offline:
            which = ", ".join(str(sa) for sa in offline)
            if on_bus is not None and len(on_bus) > 1:
                raise CommandRefused(
                    409,
                    "unit_offline",
                    f"unit{'s' if len(offline) > 1 else ''} {which} of {st.ref.vehicle_id} "
                    f"{'are' if len(offline) > 1 else 'is'} offline, and this write reaches "
                    f"every equalizer on bus {st.ref.bus}",
                )
            raise CommandRefused(
                409, "unit_offline", f"unit {which} of {st.ref.vehicle_id} is offline"
            )
        self._check_path(st.ref.bus)

    def _check_path(self, bus: str) -> None:
        """Refuse unless this gateway, or another one on the database, transmits on `bus`."""
        if bus not in self.writers and not (self._routable is not None and self._routable(bus)):
            raise CommandRefused(409, "no_bus", f"this gateway cannot transmit on bus {bus!r}")

    async def submit(
        self,
        kind: CommandKind,
        vehicle_id: str,
        body: Mapping[str, Json],
        who: Submitter,
        idempotency_key: str | None = None,
        *,
        charge: Callable[[], Awaitable[None]] | None = None,
    ) -> tuple[Command, bool]:
        """Queue a command; returns (command, created). Raises CommandRefused.

        `charge` is awaited for every attempt but the retry of a command already made (same
        Idempotency-Key), which gets that command: the API counts writes against the key's
        rate limit there, and a 429 it raises ends the attempt."""
        async with self._submit_lock:
            earlier = await self._made_with(who, idempotency_key)
            if earlier is not None:
                return _replayed(earlier, kind, vehicle_id, body), False
            if charge is not None:
                await charge()
            cmd = self._new_command(kind, vehicle_id, body, who, idempotency_key)
            return await self._enqueue(cmd, body)

    async def _made_with(self, who: Submitter, idempotency_key: str | None) -> Command | None:
        """The command the caller's key already made with this Idempotency-Key, if any."""
        if idempotency_key is None or who.key_id is None:
            return None
        return await self._db(q.command_by_idempotency, who.key_id, idempotency_key)

    def _new_command(
        self,
        kind: CommandKind,
        vehicle_id: str,
        body: Mapping[str, Json],
        who: Submitter,
        idempotency_key: str | None,
    ) -> Command:
        """The command a request makes, checked (raises CommandRefused), not yet queued."""
        target = self._addressed(kind, vehicle_id, body)
        payload = target.payload
        payload["affected_units"] = affected_units(target.on_bus)
        expiry = self._expiry(body)
        now = time.time()
        st = target.unit
        return Command(
            id=str(uuid.uuid4()),
            kind=CommandKind(kind),
            vehicle_id=st.ref.vehicle_id,
            bus=st.ref.bus,
            sa=st.ref.sa,
            payload=payload,
            state=CommandState.QUEUED,
            reason=None,
            created_at=now,
            updated_at=now,
            expires_at=now + float(expiry),
            first_sent_at=None,
            last_sent_at=None,
            sends=0,
            max_sends=target.max_sends,
            handed_at=None,
            frames_handed=0,
            key_id=who.key_id,
            key_name=who.key_name,
            idempotency_key=idempotency_key,
        )

    def _addressed(
        self, kind: CommandKind, vehicle_id: str, body: Mapping[str, Json]
    ) -> _Addressed:
        """The units a command of `kind` reaches, all online and on a bus some gateway
        transmits on, and its checked payload."""
        if kind in (CommandKind.CONTROL, CommandKind.PARAMETERS):
            # PGN 65490 and 65491 are broadcasts: every unit on the bus acts on them.
            st, on_bus = self._bus_units(vehicle_id, body)
            self._check_online(st, on_bus)
            units = [u for _, u in on_bus if u is not None]
            if kind == CommandKind.CONTROL:
                return _Addressed(st, on_bus, control_payload(units, body), 1_000_000)
            payload = parameter_payload(units, body)
            return _Addressed(st, on_bus, payload, self.settings.parameter_sends)
        if kind == CommandKind.REQUEST:
            st = self._unit(vehicle_id, _sa(body.get("unit")))
            self._check_online(st)
            # A request is addressed to one unit.
            return _Addressed(
                st, [(st.ref.sa, st)], request_payload(body), self.settings.request_sends
            )
        raise ValueError(f"unknown command kind {kind!r}")

    def _expiry(self, body: Mapping[str, Json]) -> float:
        """Seconds the command may wait to be sent: the request's `expires_in_s` (refused past
        the maximum), else the default."""
        expiry = _seconds(body.get("expires_in_s")) or self.settings.command_expiry_s
        if expiry > self.settings.command_max_expiry_s:
            raise CommandRefused(
                422,
                "invalid_expiry",
                f"expires_in_s is at most {self.settings.command_max_expiry_s:g}",
            )
        return expiry

    async def _enqueue(self, cmd: Command, body: Mapping[str, Json]) -> tuple[Command, bool]:
        """Queue `cmd` (or get the command its Idempotency-Key made meanwhile through another
        gateway), deliver it from here if this gateway transmits on its bus, announce it."""
        # Until it is queued here, a reload must not take the row from the database: a
        # round could deliver that copy too (a first send twice), and announce it as
        # sending before this announces it as queued.
        self._submitting.add(cmd.id)
        try:
            queued, created = await self._db_serialized(self._queue, cmd, body)
            if created and cmd.bus in self.writers:
                self._pending[cmd.id] = cmd
        finally:
            self._submitting.discard(cmd.id)
        if not created:  # the same Idempotency-Key, used through another gateway meanwhile
            return queued, False
        self._publish(cmd)
        self._wake.set()
        return dataclasses.replace(cmd), True

    def _queue(
        self, conn: Connection, row: Command, body: Mapping[str, Json]
    ) -> tuple[Command, bool]:
        """In one transaction holding the bus's command lock (and the Idempotency-Key's):
        the command this key already made, or a refusal if a pending command of the bus
        conflicts, or the row inserted. Every gateway on the database queues through here,
        so of two conflicting commands exactly one is accepted."""
        idem = row.idempotency_key
        key = (row.key_id, idem) if idem is not None and row.key_id is not None else None
        q.lock_command_queue(conn, row.bus, key)
        if key is not None:
            earlier = q.command_by_idempotency(conn, *key)
            if earlier is not None:
                return _replayed(earlier, row.kind, row.vehicle_id, body), False
        for other in q.pending_commands(conn, [row.bus], unexpired_at=row.created_at):
            if other.kind != row.kind:
                continue
            # Control and parameters are broadcasts: any of the bus's conflicts; a request
            # is addressed to one unit.
            if row.kind == CommandKind.REQUEST and other.sa != row.sa:
                continue
            overlap = conflict(other, row)
            if overlap:
                raise CommandRefused(
                    409,
                    "conflict",
                    f"command {other.id} for {', '.join(sorted(targets(other)))} "
                    f"on bus {other.bus} is still {other.state} and conflicts over "
                    f"{', '.join(sorted(overlap))}: wait for it or cancel it",
                    command_id=other.id,
                )
        q.insert_command(conn, row)
        return row, True

    async def cancel(self, command_id: str, who: Submitter) -> Command:
        """Cancel a pending command; raises CommandRefused when it already ended."""
        done = await self._end(command_id, life.Cancel(who.key_name)) is not None
        row = await self._db(q.get_command, command_id)
        if row is None:
            raise CommandRefused(404, "unknown_command", f"no command {command_id}")
        if not done:
            raise CommandRefused(
                409, "command_ended", f"command {command_id} is already {row.state}"
            )
        return row


def _sa(unit: Json) -> int | None:
    """The `unit` of a request body (validated at the API edge: an int or absent)."""
    return unit if isinstance(unit, int) else None


def _seconds(value: Json) -> float | None:
    """The `expires_in_s` of a request body (validated at the API edge: a number or absent)."""
    return value if isinstance(value, int | float) and not isinstance(value, bool) else None
