"""The command queue: refuse what cannot be sent, queue the rest as rows, deliver and confirm.

Nothing stale (a command past its expiry is never sent), nothing unauthorized (the API checks
roles before calling in), nothing silent (every command ends in a final state with a reason).
Control and parameter messages repeat at the manuals' 1 s until the status flags confirm a control
command, or a fixed number of sends for parameter writes (which have no read-back).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import time
import uuid
from collections import Counter
from collections.abc import Awaitable, Callable, Mapping
from dataclasses import dataclass, field
from datetime import UTC, datetime
from typing import Any, Concatenate

from sqlalchemy import Connection, Engine

from eqgw.api.settings import ApiSettings
from eqgw.bus.config import BusConfig
from eqgw.bus.errors import BusError, BusSendError
from eqgw.bus.writer import BusWriter
from eqgw.commands import lifecycle as life
from eqgw.commands import repository as q
from eqgw.commands.model import FINAL_STATES, CommandKind
from eqgw.describe import describe
from eqgw.ingest.events import Event, UnitRef
from eqgw.ingest.hub import EventHub
from eqgw.ingest.state import LiveState, UnitState
from eqgw.protocol.encode import Frame, encode
from eqgw.protocol.errors import EncodeError
from eqgw.protocol.j1939 import (
    DEFAULT_GATEWAY_SA,
    PGN_COMPONENT_ID,
    PGN_CONTROL,
    PGN_DM1,
    PGN_PARAMETERS,
    PGN_SOFTWARE_ID,
)
from eqgw.protocol.params import FACTORY_RESET, encode_parameter_write, validate_parameter_write
from eqgw.security import repository as security_q
from eqgw.store.transaction import P, R, run_in_transaction
from eqgw.tasks import STOP_TIMEOUT_S, cancel_and_wait

log = logging.getLogger(__name__)

COMMAND_EVENT = "command"

# How long past its expiry a never-sent command for a bus this gateway does not deliver on
# waits before this gateway ends it (the owner, if there is one, ends it first).
UNOWNED_EXPIRY_GRACE_S = 5.0

# The live slot of a unit's latest Acknowledgement (PGN 59392) record.
ACK_SLOT = "acknowledgement"

# API field -> (control signal, status flag that confirms it).
CONTROL_FIELDS: dict[str, tuple[str, str]] = {
    "jump_start_override": ("can_jso", "state_can_jso"),
    "can_onoff_enable": ("can_onoff_en", "state_onoff_en"),
    "equalizer_on": ("can_eq_onoff", "eq_state_onoff"),
    "smart_sensor_messages": ("can_ss_msg_en", "can_ss_msg_on"),
}
# What a unit can be asked for -> (requested PGN, live slot of the answer).
REQUESTS: dict[str, tuple[int, str]] = {
    "dm1": (PGN_DM1, "dm1"),
    "component_id": (PGN_COMPONENT_ID, "component_id"),
    "software_id": (PGN_SOFTWARE_ID, "software_id"),
}


# Parameter writes that put every parameter of the unit back (index 0): they conflict with
# any other parameter write pending for the unit.
RESET_PARAMETERS = frozenset({FACTORY_RESET, "profile"})


class CommandRefused(Exception):
    """A command that must not be queued: HTTP status, stable type, reason."""

    def __init__(self, status: int, type_: str, detail: str, **extra: Any) -> None:
        super().__init__(detail)
        self.status = status
        self.type = type_
        self.detail = detail
        self.extra = extra


@dataclass(slots=True)
class Submitter:
    """Who submits: the key (None for internal use)."""

    key_id: int | None
    key_name: str | None


@dataclass(slots=True)
class _Tracking:
    """In-memory delivery state of a pending command (baselines for confirmation)."""

    # Per unit reached: the time of its latest answer slot (status) before the first send.
    baselines: dict[int, float | None] = field(default_factory=dict)
    # Per unit reached: the time of its latest acknowledgement (PGN 59392) before the first send.
    ack_baselines: dict[int, float | None] = field(default_factory=dict)
    last_bus_error: str | None = None
    last_attempt: float = field(default=-math.inf)


class CommandService:
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
    ) -> None:
        self.engine = engine
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
        self._pending: dict[str, dict[str, Any]] = {}
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
        self._task = asyncio.create_task(self._run(), name="command delivery")

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
        for cid in [cid for cid, cmd in self._pending.items() if cmd["bus"] == bus]:
            self._pending.pop(cid, None)
            self._tracking.pop(cid, None)

    def poke(self) -> None:
        """Look for commands queued elsewhere now instead of at the next periodic reload."""
        self._reload_now = True
        self._wake.set()

    def delivers(self, bus: str) -> bool:
        """Whether this process transmits on `bus` now."""
        return bus in self.writers

    async def _db(
        self, fn: Callable[Concatenate[Connection, P], R], /, *args: P.args, **kwargs: P.kwargs
    ) -> R:
        return await run_in_transaction(self.engine, fn, *args, **kwargs)

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
        self, vehicle_id: str, body: Mapping[str, Any]
    ) -> tuple[UnitState, list[tuple[int, UnitState | None]]]:
        """For a broadcast (control, parameters): the unit the record is filed under and every
        unit known on its bus, heard or configured, by SA (None: configured, never heard).

        Refused unless the request says it knows, `all_units`, when the bus has several."""
        sa = body.get("unit")
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
        offline = [
            sa
            for sa, u in reached
            if u is None
            or "OFFLINE" in u.faults.open
            or u.last_seen is None
            or u.faults.parked_since is not None
        ]
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

    def _control_payload(self, units: list[UnitState], body: Mapping[str, Any]) -> dict[str, Any]:
        """Control fields checked against every unit on the bus (each one acts on them)."""
        wanted = {k: body[k] for k in CONTROL_FIELDS if body.get(k) is not None}
        if not wanted:
            raise CommandRefused(422, "empty_command", "no control field given: nothing to do")
        if "smart_sensor_messages" in wanted:
            others = [u for u in units if u.series != 70]
            if others:
                if len(units) == 1:
                    series = _series_text(others[0].series)
                    which = f"this unit is {series}"
                else:
                    which = "it reaches " + ", ".join(
                        f"unit {u.ref.sa} ({_series_text(u.series)})" for u in others
                    )
                raise CommandRefused(
                    422,
                    "unsupported_field",
                    f"smart_sensor_messages exists only on the 70-series; {which}",
                )
        if "equalizer_on" in wanted:
            enable = wanted.get("can_onoff_enable")
            if enable is False:
                raise CommandRefused(
                    422,
                    "contradictory",
                    "equalizer_on needs CAN on/off enabled; this command disables it",
                )
            off = [u for u in units if (u.status_flags or {}).get("state_onoff_en") != "active"]
            if enable is None and off:
                which = (
                    "it is not"
                    if len(units) == 1
                    else "on unit " + ", ".join(str(u.ref.sa) for u in off) + " it is not"
                )
                raise CommandRefused(
                    409,
                    "onoff_not_enabled",
                    f"equalizer on/off works only while CAN on/off is enabled, and {which}: "
                    "add `can_onoff_enable: true` to this command to enable it first",
                )
        fields = {CONTROL_FIELDS[k][0]: ("enable" if v else "disable") for k, v in wanted.items()}
        expect = {CONTROL_FIELDS[k][1]: ("active" if v else "inactive") for k, v in wanted.items()}
        return {"request": dict(body), "fields": fields, "expect": expect}

    def _parameter_payload(self, units: list[UnitState], body: Mapping[str, Any]) -> dict[str, Any]:
        """A parameter write validated against every unit on the bus (each one applies it);
        a reason that holds for some of them only names them."""
        values = {k: v for k, v in body.items() if k not in ("unit", "expires_in_s", "all_units")}
        by_reason: dict[str, list[UnitState]] = {}
        for u in units:
            for reason in validate_parameter_write(values, u.series):
                by_reason.setdefault(reason, []).append(u)
        reasons = [
            reason
            if len(who) == len(units)
            else ", ".join(f"unit {u.ref.sa}" for u in who) + f": {reason}"
            for reason, who in by_reason.items()
        ]
        if reasons:
            kind = "unsupported_field" if all("not supported" in r for r in reasons) else None
            raise CommandRefused(
                422, kind or "invalid_parameters", "; ".join(reasons), reasons=reasons
            )
        return {"request": dict(body), "values": values}

    def _request_payload(self, body: Mapping[str, Any]) -> dict[str, Any]:
        what = body.get("what")
        if what not in REQUESTS:
            raise CommandRefused(422, "invalid_request", f"cannot request {what!r}")
        pgn, slot = REQUESTS[what]
        return {"request": dict(body), "what": what, "pgn": pgn, "slot": slot}

    @staticmethod
    def _targets(cmd: Mapping[str, Any]) -> set[str]:
        p = cmd["payload"]
        if cmd["kind"] == "control":
            return set(p["fields"])
        if cmd["kind"] == "parameters":
            return set(p["values"])
        return {p["what"]}

    @classmethod
    def _conflict(cls, pending: Mapping[str, Any], new: Mapping[str, Any]) -> set[str]:
        """What two commands of one kind for one unit (or bus) would fight over: the same
        field, or one undoing the other. Disabling CAN on/off takes equalizer on/off out of
        the gateway's hands; a factory reset (or a reset profile) puts every parameter back."""
        a, b = cls._targets(pending), cls._targets(new)
        clash = a & b
        if new["kind"] == "control":
            for x, y in ((pending, new), (new, pending)):
                if x["payload"]["fields"].get("can_onoff_en") == "disable" and (
                    "can_eq_onoff" in y["payload"]["fields"]
                ):
                    clash |= {"can_onoff_en", "can_eq_onoff"}
        elif new["kind"] == "parameters" and a and b and (a | b) & RESET_PARAMETERS:
            clash |= (a | b) & RESET_PARAMETERS
        return clash

    async def submit(
        self,
        kind: str,
        vehicle_id: str,
        body: Mapping[str, Any],
        who: Submitter,
        idempotency_key: str | None = None,
        *,
        charge: Callable[[], Awaitable[None]] | None = None,
    ) -> tuple[dict[str, Any], bool]:
        """Queue a command; returns (command, created). Raises CommandRefused.

        `charge` is awaited for every attempt but the retry of a command already made (same
        Idempotency-Key), which gets that command: the API counts writes against the key's
        rate limit there, and a 429 it raises ends the attempt."""
        async with self._submit_lock:
            if idempotency_key is not None and who.key_id is not None:
                earlier = await self._db(q.command_by_idempotency, who.key_id, idempotency_key)
                if earlier is not None:
                    return _replayed(earlier, kind, vehicle_id, body), False
            if charge is not None:
                await charge()
            if kind in ("control", "parameters"):
                # PGN 65490 and 65491 are broadcasts: every unit on the bus acts on them.
                st, on_bus = self._bus_units(vehicle_id, body)
                self._check_online(st, on_bus)
                units = [u for _, u in on_bus if u is not None]
                if kind == "control":
                    payload = self._control_payload(units, body)
                    max_sends = 1_000_000
                else:
                    payload = self._parameter_payload(units, body)
                    max_sends = self.settings.parameter_sends
            elif kind == "request":
                st = self._unit(vehicle_id, body.get("unit"))
                self._check_online(st)
                on_bus = [(st.ref.sa, st)]  # a request is addressed to one unit
                payload = self._request_payload(body)
                max_sends = self.settings.request_sends
            else:
                raise ValueError(f"unknown command kind {kind!r}")
            payload["affected_units"] = affected_units(on_bus)
            expiry = body.get("expires_in_s") or self.settings.command_expiry_s
            if expiry > self.settings.command_max_expiry_s:
                raise CommandRefused(
                    422,
                    "invalid_expiry",
                    f"expires_in_s is at most {self.settings.command_max_expiry_s:g}",
                )
            now = time.time()
            row: dict[str, Any] = {
                "id": str(uuid.uuid4()),
                "kind": kind,
                "vehicle_id": st.ref.vehicle_id,
                "bus": st.ref.bus,
                "sa": st.ref.sa,
                "payload": payload,
                "state": "queued",
                "reason": None,
                "created_at": now,
                "updated_at": now,
                "expires_at": now + float(expiry),
                "first_sent_at": None,
                "last_sent_at": None,
                "sends": 0,
                "max_sends": max_sends,
                "handed_at": None,
                "frames_handed": 0,
                "key_id": who.key_id,
                "key_name": who.key_name,
                "idempotency_key": idempotency_key,
            }
            # Until it is queued here, a reload must not take the row from the database: a
            # round could deliver that copy too (a first send twice), and announce it as
            # sending before this announces it as queued.
            self._submitting.add(row["id"])
            try:
                queued, created = await self._db_serialized(self._queue, row, body)
                if created and row["bus"] in self.writers:
                    self._pending[row["id"]] = row
            finally:
                self._submitting.discard(row["id"])
            if not created:  # the same Idempotency-Key, used through another gateway meanwhile
                return queued, False
            self._publish(row)
            self._wake.set()
            return dict(row), True

    def _queue(
        self, conn: Connection, row: dict[str, Any], body: Mapping[str, Any]
    ) -> tuple[dict[str, Any], bool]:
        """In one transaction holding the bus's command lock (and the Idempotency-Key's):
        the command this key already made, or a refusal if a pending command of the bus
        conflicts, or the row inserted. Every gateway on the database queues through here,
        so of two conflicting commands exactly one is accepted."""
        idem = row["idempotency_key"]
        key = (row["key_id"], idem) if idem is not None and row["key_id"] is not None else None
        q.lock_command_queue(conn, row["bus"], key)
        if key is not None:
            earlier = q.command_by_idempotency(conn, *key)
            if earlier is not None:
                return _replayed(earlier, row["kind"], row["vehicle_id"], body), False
        for other in q.pending_commands(conn, [row["bus"]], unexpired_at=row["created_at"]):
            if other["kind"] != row["kind"]:
                continue
            # Control and parameters are broadcasts: any of the bus's conflicts; a request
            # is addressed to one unit.
            if row["kind"] == "request" and other["sa"] != row["sa"]:
                continue
            overlap = self._conflict(other, row)
            if overlap:
                raise CommandRefused(
                    409,
                    "conflict",
                    f"command {other['id']} for {', '.join(sorted(self._targets(other)))} "
                    f"on bus {other['bus']} is still {other['state']} and conflicts over "
                    f"{', '.join(sorted(overlap))}: wait for it or cancel it",
                    command_id=other["id"],
                )
        q.insert_command(conn, row)
        return row, True

    async def _db_serialized(self, fn: Callable[..., Any], *args: Any) -> Any:
        """Run `fn(conn, *args)` in a transaction that, on SQLite, holds the write lock from
        its start (so what it reads cannot change before it writes)."""

        def run() -> Any:
            with self._serial_engine.begin() as conn:
                return fn(conn, *args)

        return await asyncio.to_thread(run)

    async def cancel(self, command_id: str, who: Submitter) -> dict[str, Any]:
        """Cancel a pending command; raises CommandRefused when it already ended."""
        done = await self._end(command_id, life.Cancel(who.key_name)) is not None
        row = await self._db(q.get_command, command_id)
        if row is None:
            raise CommandRefused(404, "unknown_command", f"no command {command_id}")
        if not done:
            raise CommandRefused(
                409, "command_ended", f"command {command_id} is already {row['state']}"
            )
        return dict(row)

    # -- delivery -----------------------------------------------------------------------------

    async def _reload(self) -> None:
        self._reload_now = False
        buses = list(self.writers)
        rows: list[dict[str, Any]] = await self._db(q.pending_commands, buses)
        # Ended by another process (cancelled through an API-only instance): stop sending.
        # Only a row read as ended counts (one just submitted here may postdate the query).
        still = {row["id"] for row in rows}
        missing = [cid for cid, cmd in self._pending.items()
                   if cid not in still and cmd["bus"] in buses]  # fmt: skip
        ended = await self._db(q.ended_commands, missing) if missing else {}
        for cid, final in ended.items():
            gone = self._pending.pop(cid, None)
            self._tracking.pop(cid, None)
            if gone is not None:
                gone.update(final)
        for row in rows:
            # The bus not given up while the query ran; the row not one being submitted here.
            if row["bus"] in self.writers and row["id"] not in self._submitting:
                self._pending.setdefault(row["id"], row)
        # Commands for buses nobody here delivers on, never sent and past their expiry: the
        # owner would end them, but there may be none (its gateway down, the bus unreachable).
        # A grace past the expiry: an owner's send just before it may not be recorded yet.
        now = time.time()
        before = now - UNOWNED_EXPIRY_GRACE_S
        for cmd in await self._db_serialized(q.end_unowned, buses, before, _abandoned, now):
            await self._ended(cmd, now)

    async def _run(self) -> None:
        last_reload = time.monotonic()
        failures = 0
        while True:
            # After a failed round (the database away), wait longer each time, up to 5 s.
            wait = self.settings.delivery_poll_s if not failures else min(0.5 * failures, 5.0)
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout(wait):
                    await self._wake.wait()
            self._wake.clear()
            try:
                if self._reload_now or time.monotonic() - last_reload >= 1.0:
                    # Commands queued by another process (e.g. an API-only instance).
                    await self._reload()
                    last_reload = time.monotonic()
                for cmd in list(self._pending.values()):
                    await self._step(cmd)
            except Exception as exc:  # the database may be away: retry on the next round
                failures += 1
                # The first failure with its traceback, then one line every 10 in a row.
                if failures == 1:
                    log.exception("command delivery round failed; retrying")
                elif failures % 10 == 0:
                    log.warning("command delivery rounds failing (%d in a row): %s",
                                failures, describe(exc))  # fmt: skip
            else:
                if failures:
                    log.warning("command delivery resumed after %d failed rounds", failures)
                failures = 0

    def _answers(self, cmd: Mapping[str, Any], slot: str) -> list[tuple[int, life.Answer | None]]:
        """Per unit the command reaches, its latest record in the live `slot`."""
        out: list[tuple[int, life.Answer | None]] = []
        for sa in command_units(cmd):
            st = self.live.get(cmd["bus"], sa)
            out.append((sa, st.latest.get(slot) if st is not None else None))
        return out

    def _confirmed(self, cmd: dict[str, Any], track: _Tracking) -> bool:
        """Whether every unit the command reaches has answered since the first send
        (`lifecycle.confirmed`)."""
        p = cmd["payload"]
        slot = "status" if cmd["kind"] == "control" else p.get("slot")
        answers = None if slot is None else self._answers(cmd, slot)
        kind = CommandKind(cmd["kind"])
        return life.confirmed(
            kind, cmd["first_sent_at"], p.get("expect", {}), answers, track.baselines
        )

    def _series(self, cmd: dict[str, Any]) -> int | None:
        """The series of every unit the command reaches if they share one, else None (then
        only what both series accept is encoded, as validation allowed)."""
        found = set()
        for sa in command_units(cmd):
            st = self.live.get(cmd["bus"], sa)
            found.add(st.series if st is not None else None)
        return found.pop() if len(found) == 1 else None

    def _frames(self, cmd: dict[str, Any], writer: BusWriter) -> list[Frame]:
        p = cmd["payload"]
        series = self._series(cmd)
        gw = writer.gateway_sa
        if cmd["kind"] == "control":
            return encode("control", p["fields"], sa=gw, series=series or 80)
        if cmd["kind"] == "parameters":
            return encode_parameter_write(p["values"], sa=gw, series=series, da=cmd["sa"])
        order = self.buses[cmd["bus"]].request_byte_order if cmd["bus"] in self.buses else "lsb"
        return encode(
            "request",
            {"requested_pgn": p["pgn"], "da": cmd["sa"]},
            sa=gw,
            request_byte_order=order,
        )

    def _refusal(self, cmd: dict[str, Any], track: _Tracking) -> str | None:
        """Why to end a command as refused: a unit it reaches answered it with a NACK or
        "access denied" (`lifecycle.refusal`); else None."""
        if cmd["handed_at"] is None:
            return None
        bus = self.buses.get(cmd["bus"])
        writer = self.writers.get(cmd["bus"])
        gateway = bus.gateway_sa if bus else writer.gateway_sa if writer else DEFAULT_GATEWAY_SA
        return life.refusal(
            cmd["handed_at"],
            self._answers(cmd, ACK_SLOT),
            track.ack_baselines,
            command_pgn(cmd),
            gateway,
        )

    def _baselines(self, cmd: dict[str, Any], slot: str | None = None) -> dict[int, float | None]:
        """Per unit reached, when its latest answer slot (or `slot`) arrived (before the
        first send)."""
        if slot is None:
            slot = "status" if cmd["kind"] == "control" else cmd["payload"].get("slot")
        out: dict[int, float | None] = {}
        for sa in command_units(cmd):
            st = self.live.get(cmd["bus"], sa)
            latest = st.latest.get(slot) if st is not None and slot is not None else None
            out[sa] = latest[0] if latest else None
        return out

    def _live(self, cmd: Mapping[str, Any]) -> bool:
        """Whether a command is still this process's to deliver (not ended meanwhile)."""
        return cmd["state"] not in FINAL_STATES and self._pending.get(cmd["id"]) is cmd

    async def _step(self, cmd: dict[str, Any]) -> None:
        """One delivery step of a pending command: gather the facts, let the lifecycle
        decide, do what it decided."""
        if not self._live(cmd):
            return  # ended (cancelled) earlier in this round
        track = self._tracking.setdefault(cmd["id"], _Tracking())
        now = time.time()
        decision: life.Step | life.Send | life.Release = life.step(
            life.Situation(
                kind=CommandKind(cmd["kind"]),
                now=now,
                expires_at=cmd["expires_at"],
                sends=cmd["sends"],
                max_sends=cmd["max_sends"],
                last_sent_at=cmd["last_sent_at"],
                last_attempt=track.last_attempt,
                resend_interval_s=self.settings.resend_interval_s,
                confirmed=self._confirmed(cmd, track),
                refusal=self._refusal(cmd, track),
                last_bus_error=track.last_bus_error,
            )
        )
        if isinstance(decision, life.Due):
            decision = life.route(self._path(cmd["bus"]), cmd["bus"])
        match decision:
            case life.Finish(state, reason):
                await self._finish(cmd, state, reason)
            case life.End(cause):
                await self._end(cmd["id"], cause)
            case life.Release():
                self._release(cmd["id"])  # another gateway owns the bus now
            case life.Send():
                await self._round(cmd, track, now)

    def _path(self, bus: str) -> life.Path:
        if bus in self.writers:
            return life.Path.OWN
        if self._routable is not None and self._routable(bus):
            return life.Path.ELSEWHERE
        return life.Path.NONE

    def _release(self, command_id: str) -> None:
        """Stop delivering a command here (ended elsewhere, or its bus owned elsewhere)."""
        self._pending.pop(command_id, None)
        self._tracking.pop(command_id, None)

    async def _round(self, cmd: dict[str, Any], track: _Tracking, now: float) -> None:
        """A delivery round: record the hand-over ahead, hand every frame to the interface,
        record what went."""
        writer = self.writers[cmd["bus"]]
        try:
            frames = self._frames(cmd, writer)
        except (EncodeError, ValueError) as exc:
            await self._end(cmd["id"], life.unencodable(str(exc)).cause)
            return
        track.last_attempt = now
        if cmd["sends"] == 0:
            track.baselines = self._baselines(cmd)
            track.ack_baselines = self._baselines(cmd, ACK_SLOT)
        # Written ahead of the hand-over, and only while the command is pending: once it is
        # recorded nothing reports the command as unsent (a death or a failed record right
        # after a frame left included), and a command ended meanwhile (cancelled through
        # another process) is never handed over again.
        before = {"state": cmd["state"], "handed_at": cmd["handed_at"]}
        ahead = life.hand_over_mark(cmd["handed_at"], now)
        if not await self._db(q.update_command, cmd["id"], dict(ahead)):
            self._release(cmd["id"])  # ended elsewhere
            return
        cmd.update(ahead)
        handed = await self._hand_over(cmd, track, writer, frames)
        outcome = life.after_round(len(frames), handed, before["handed_at"] is not None)
        if outcome is life.RoundOutcome.PARTIAL:
            # An incomplete round is not a send; what of it may have left is counted.
            cmd["frames_handed"] += handed
            await self._db(q.add_frames_handed, cmd["id"], handed)
        elif outcome is life.RoundOutcome.TAKE_BACK:
            # Provably nothing handed over (the bus refused every frame before the
            # hand-over, or the command ended first): as unsent as before the round.
            if await self._db(q.update_command, cmd["id"], before):
                cmd.update(before)
        elif outcome is life.RoundOutcome.COMPLETE:
            values = life.record_send(cmd["sends"], cmd["first_sent_at"], time.time())
            if await self._db(q.update_command, cmd["id"], dict(values)):
                first = cmd["sends"] == 0
                cmd.update(values)
                if first:
                    self._publish(cmd)
            else:
                self._pending.pop(cmd["id"], None)  # ended elsewhere (cancelled)

    async def _hand_over(
        self, cmd: dict[str, Any], track: _Tracking, writer: BusWriter, frames: list[Frame]
    ) -> int:
        """Hand a round's frames to the interface; how many went (a send that failed after
        the interface may have taken its frame counts it)."""
        handed = 0
        try:
            for can_id, data in frames:
                # Re-check right before each frame: a command that expired, or ended (was
                # cancelled) while this round waited on another command's send, never
                # reaches the bus. The send itself gives up at the expiry.
                if not life.may_hand(time.time(), cmd["expires_at"], self._live(cmd)):
                    break
                await writer.send(can_id, data, deadline=cmd["expires_at"])
                handed += 1
                self.frames_sent += 1
        except BusError as exc:
            track.last_bus_error = str(exc)
            if isinstance(exc, BusSendError) and exc.handed:
                handed += 1
        return handed

    async def _finish(self, cmd: dict[str, Any], state: str, reason: str) -> None:
        now = time.time()
        values = {"state": state, "reason": reason, "updated_at": now}
        if await self._db(q.update_command, cmd["id"], values):
            cmd.update(values)
            await self._ended(cmd, now)
        self._pending.pop(cmd["id"], None)
        self._tracking.pop(cmd["id"], None)

    async def _ended(self, cmd: dict[str, Any], now: float) -> None:
        """Count, publish and audit a command that just reached its final state."""
        state, reason = cmd["state"], cmd["reason"]
        self.outcomes[(cmd["kind"], state)] += 1
        self._publish(cmd)
        await self._db(
            security_q.add_audit,
            {
                "ts": now,
                "key_id": cmd["key_id"],
                "key_name": cmd["key_name"],
                "role": None,
                "action": f"command.{cmd['kind']}.{state}",
                "vehicle_id": cmd["vehicle_id"],
                "target": command_target(cmd),
                "request": None,
                "outcome": state,
                "status_code": 200,
                "detail": reason,
                "command_id": cmd["id"],
            },
        )

    async def _end(self, command_id: str, cause: life.EndCause) -> dict[str, Any] | None:
        """End a pending command as the lifecycle decides for `cause` from its row locked as
        it is now (so a hand-over recorded by a delivery round is seen); the ended command,
        or None when it was no longer pending."""
        now = time.time()
        row = await self._db_serialized(q.end_command, command_id, _decide(cause), now)
        cmd = self._pending.pop(command_id, None)
        self._tracking.pop(command_id, None)
        if row is None:
            return None
        if cmd is None:
            cmd = row
        else:
            cmd.update(row)
        await self._ended(cmd, now)
        return cmd

    def _publish(self, cmd: Mapping[str, Any]) -> None:
        ref = UnitRef(cmd["vehicle_id"], cmd["bus"], cmd["sa"])
        self.hub.publish(Event(COMMAND_EVENT, ref, time.time(), public_command(cmd)))


def _record(row: Mapping[str, Any]) -> life.Record:
    """What a command's row shows of its hand-over."""
    return life.Record(
        CommandKind(row["kind"]), row["handed_at"], row["sends"], row["frames_handed"]
    )


def _decide(cause: life.EndCause) -> q.Decide:
    """How a command ends for `cause`, decided from its row when it ends."""

    def decide(row: Mapping[str, Any]) -> tuple[str, str]:
        end = life.ending(cause, _record(row))
        return end.state, end.reason

    return decide


def _abandoned(row: Mapping[str, Any]) -> tuple[str, str]:
    """How a command past its expiry on a bus no running gateway delivers on ends."""
    return _decide(life.Abandoned(row["bus"]))(row)


def _series_text(series: int | None) -> str:
    return "an unknown series" if series is None else f"the {series}-series"


def affected_units(on_bus: list[tuple[int, UnitState | None]]) -> list[dict[str, Any]]:
    """The units a command reaches, as the API shows them: SA and series (None: unknown)."""
    return [{"sa": sa, "series": st.series if st is not None else None} for sa, st in on_bus]


def command_units(cmd: Mapping[str, Any]) -> list[int]:
    """The SAs of the units a command reaches (commands queued before this was recorded:
    the one unit they name)."""
    units = cmd["payload"].get("affected_units")
    return [u["sa"] for u in units] if units else [cmd["sa"]]


def command_pgn(cmd: Mapping[str, Any]) -> int:
    """The PGN a unit's acknowledgement of this command names: the control or parameter PGN,
    or for a request the PGN requested."""
    if cmd["kind"] == "control":
        return PGN_CONTROL
    if cmd["kind"] == "parameters":
        return PGN_PARAMETERS
    pgn: int = cmd["payload"]["pgn"]
    return pgn


def command_target(cmd: Mapping[str, Any]) -> str:
    """`bus/SA,SA,...`: where a command goes, for the audit log."""
    return f"{cmd['bus']}/{','.join(str(sa) for sa in command_units(cmd))}"


def describe_reach(cmd: Mapping[str, Any]) -> str:
    """One line for the audit log: the bus and every unit the command reaches."""
    units = cmd["payload"].get("affected_units") or [{"sa": cmd["sa"], "series": None}]
    listed = ", ".join(
        f"{u['sa']} ({u['series']}-series)" if u["series"] else f"{u['sa']} (series unknown)"
        for u in units
    )
    return f"reaches bus {cmd['bus']}, unit{'s' if len(units) > 1 else ''} {listed}"


def _replayed(
    earlier: dict[str, Any], kind: str, vehicle_id: str, body: Mapping[str, Any]
) -> dict[str, Any]:
    """The command made earlier with this Idempotency-Key, if the request is the same."""
    if (
        earlier["kind"] != kind
        or earlier["vehicle_id"] != vehicle_id
        or dict(earlier["payload"].get("request", {})) != dict(body)
    ):
        raise CommandRefused(
            422,
            "idempotency_key_reused",
            "this Idempotency-Key was used for a different request",
            command_id=earlier["id"],
        )
    return earlier


def public_command(cmd: Mapping[str, Any]) -> dict[str, Any]:
    """A command as the API shows it."""
    p = cmd["payload"]
    return {
        "id": cmd["id"],
        "kind": cmd["kind"],
        "vehicle_id": cmd["vehicle_id"],
        "bus": cmd["bus"],
        "unit": cmd["sa"],
        "affected_units": p.get("affected_units") or [{"sa": cmd["sa"], "series": None}],
        "request": p.get("request"),
        "state": cmd["state"],
        "reason": cmd["reason"],
        "created_at": cmd["created_at"],
        "updated_at": cmd["updated_at"],
        "expires_at": cmd["expires_at"],
        "first_sent_at": cmd["first_sent_at"],
        "last_sent_at": cmd["last_sent_at"],
        "sends": cmd["sends"],
        "key_name": cmd["key_name"],
    }
