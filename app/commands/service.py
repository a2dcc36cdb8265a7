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
from typing import Any

from sqlalchemy import Engine

from app.api.settings import ApiSettings
from app.bus.config import BusConfig
from app.bus.errors import BusError
from app.bus.writer import BusWriter
from app.describe import describe
from app.ingest.events import Event, UnitRef
from app.ingest.hub import EventHub
from app.ingest.state import LiveState, UnitState
from app.protocol.encode import Frame, encode
from app.protocol.errors import EncodeError
from app.protocol.j1939 import PGN_COMPONENT_ID, PGN_DM1, PGN_SOFTWARE_ID
from app.protocol.params import FACTORY_RESET, encode_parameter_write, validate_parameter_write
from app.store import api_queries as q

log = logging.getLogger(__name__)

COMMAND_EVENT = "command"
FINAL_STATES = ("confirmed", "sent", "failed", "expired", "cancelled")
# How long past its expiry a never-sent command for a bus this gateway does not deliver on
# waits before this gateway ends it (the owner, if there is one, ends it first).
UNOWNED_EXPIRY_GRACE_S = 5.0

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

    baseline_ts: float | None = None
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

    async def stop(self) -> None:
        task, self._task = self._task, None
        if task is not None:
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await task

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

    async def _db(self, fn: Callable[..., Any], *args: Any, **kwargs: Any) -> Any:
        def run() -> Any:
            with self.engine.begin() as conn:
                return fn(conn, *args, **kwargs)

        return await asyncio.to_thread(run)

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

    def _check_online(self, st: UnitState) -> None:
        if "OFFLINE" in st.faults.open or st.last_seen is None:
            raise CommandRefused(
                409, "unit_offline", f"unit {st.ref.sa} of {st.ref.vehicle_id} is offline"
            )
        if st.ref.bus not in self.writers and not (
            self._routable is not None and self._routable(st.ref.bus)
        ):
            raise CommandRefused(
                409, "no_bus", f"this gateway cannot transmit on bus {st.ref.bus!r}"
            )

    def _control_payload(self, st: UnitState, body: Mapping[str, Any]) -> dict[str, Any]:
        wanted = {k: body[k] for k in CONTROL_FIELDS if body.get(k) is not None}
        if not wanted:
            raise CommandRefused(422, "empty_command", "no control field given: nothing to do")
        if "smart_sensor_messages" in wanted and st.series != 70:
            series = "an unknown series" if st.series is None else f"the {st.series}-series"
            raise CommandRefused(
                422,
                "unsupported_field",
                f"smart_sensor_messages exists only on the 70-series; this unit is {series}",
            )
        if "equalizer_on" in wanted:
            enable = wanted.get("can_onoff_enable")
            if enable is False:
                raise CommandRefused(
                    422,
                    "contradictory",
                    "equalizer_on needs CAN on/off enabled; this command disables it",
                )
            flags = st.status_flags or {}
            if enable is None and flags.get("state_onoff_en") != "active":
                raise CommandRefused(
                    409,
                    "onoff_not_enabled",
                    "equalizer on/off works only while CAN on/off is enabled, and it is not: "
                    "add `can_onoff_enable: true` to this command to enable it first",
                )
        fields = {CONTROL_FIELDS[k][0]: ("enable" if v else "disable") for k, v in wanted.items()}
        expect = {CONTROL_FIELDS[k][1]: ("active" if v else "inactive") for k, v in wanted.items()}
        return {"request": dict(body), "fields": fields, "expect": expect}

    def _parameter_payload(self, st: UnitState, body: Mapping[str, Any]) -> dict[str, Any]:
        values = {k: v for k, v in body.items() if k not in ("unit", "expires_in_s")}
        reasons = validate_parameter_write(values, st.series)
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
                    return earlier, False
            if charge is not None:
                await charge()
            st = self._unit(vehicle_id, body.get("unit"))
            self._check_online(st)
            if kind == "control":
                payload = self._control_payload(st, body)
                # Control (PGN 65490) is a broadcast: every unit on the bus acts on it.
                scope: dict[str, Any] = {"bus": st.ref.bus}
                max_sends = 1_000_000
            elif kind == "parameters":
                payload = self._parameter_payload(st, body)
                scope = {"bus": st.ref.bus, "sa": st.ref.sa}
                max_sends = self.settings.parameter_sends
            elif kind == "request":
                payload = self._request_payload(body)
                scope = {"bus": st.ref.bus, "sa": st.ref.sa}
                max_sends = self.settings.request_sends
            else:
                raise ValueError(f"unknown command kind {kind!r}")
            expiry = body.get("expires_in_s") or self.settings.command_expiry_s
            if expiry > self.settings.command_max_expiry_s:
                raise CommandRefused(
                    422,
                    "invalid_expiry",
                    f"expires_in_s is at most {self.settings.command_max_expiry_s:g}",
                )
            new = {"kind": kind, "payload": payload}
            if st.ref.bus in self.writers:
                pending: list[dict[str, Any]] = list(self._pending.values())
            else:  # another gateway delivers on this bus: its queue is in the database
                pending = await self._db(q.pending_commands, [st.ref.bus])
            for other in pending:
                if other["kind"] != kind or other["bus"] != scope["bus"]:
                    continue
                if "sa" in scope and other["sa"] != scope["sa"]:
                    continue
                overlap = self._conflict(other, new)
                if overlap:
                    raise CommandRefused(
                        409,
                        "conflict",
                        f"command {other['id']} for {', '.join(sorted(self._targets(other)))} "
                        f"is still {other['state']} and conflicts over "
                        f"{', '.join(sorted(overlap))}: wait for it or cancel it",
                        command_id=other["id"],
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
                "key_id": who.key_id,
                "key_name": who.key_name,
                "idempotency_key": idempotency_key,
            }
            # Until it is queued here, a reload must not take the row from the database: a
            # round could deliver that copy too (a first send twice), and announce it as
            # sending before this announces it as queued.
            self._submitting.add(row["id"])
            try:
                await self._db(q.insert_command, row)
                if row["bus"] in self.writers:
                    self._pending[row["id"]] = row
            finally:
                self._submitting.discard(row["id"])
            self._publish(row)
            self._wake.set()
            return dict(row), True

    async def cancel(self, command_id: str, who: Submitter) -> dict[str, Any]:
        """Cancel a pending command; raises CommandRefused when it already ended."""
        done = await self._finish_by_id(command_id, "cancelled", f"cancelled by {who.key_name}")
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
        for cmd in await self._db(q.expire_unsent, buses, now - UNOWNED_EXPIRY_GRACE_S):
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

    def _confirmed(self, cmd: dict[str, Any], track: _Tracking) -> bool:
        st = self.live.get(cmd["bus"], cmd["sa"])
        if st is None or cmd["first_sent_at"] is None:
            return False
        p = cmd["payload"]
        slot = "status" if cmd["kind"] == "control" else p.get("slot")
        if slot is None:
            return False
        latest = st.latest.get(slot)
        if latest is None:
            return False
        ts, fields = latest
        if track.baseline_ts is not None and ts <= track.baseline_ts:
            return False  # only frames that arrived after our first send count
        if cmd["kind"] == "control":
            return all(fields.get(flag) == want for flag, want in p["expect"].items())
        return True

    def _frames(self, cmd: dict[str, Any], writer: BusWriter) -> list[Frame]:
        p = cmd["payload"]
        st = self.live.get(cmd["bus"], cmd["sa"])
        series = st.series if st is not None else None
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

    def _baseline(self, cmd: dict[str, Any]) -> float | None:
        st = self.live.get(cmd["bus"], cmd["sa"])
        slot = "status" if cmd["kind"] == "control" else cmd["payload"].get("slot")
        if st is None or slot is None:
            return None
        latest = st.latest.get(slot)
        return latest[0] if latest else None

    def _live(self, cmd: Mapping[str, Any]) -> bool:
        """Whether a command is still this process's to deliver (not ended meanwhile)."""
        return cmd["state"] not in FINAL_STATES and self._pending.get(cmd["id"]) is cmd

    async def _step(self, cmd: dict[str, Any]) -> None:
        if not self._live(cmd):
            return  # ended (cancelled) earlier in this round
        track = self._tracking.setdefault(cmd["id"], _Tracking())
        now = time.time()
        if cmd["sends"] and self._confirmed(cmd, track):
            reason = (
                "confirmed by the status flags" if cmd["kind"] == "control" else "the unit answered"
            )
            await self._finish(cmd, "confirmed", reason)
            return
        if now >= cmd["expires_at"]:
            if cmd["sends"] == 0:
                why = f": {track.last_bus_error}" if track.last_bus_error else ""
                await self._finish(cmd, "expired", f"expired before it could be sent{why}")
            elif cmd["kind"] == "control":
                await self._finish(
                    cmd,
                    "failed",
                    f"not confirmed by the status flags before expiry ({cmd['sends']} sends)",
                )
            else:
                await self._finish(cmd, "expired", f"expired after {cmd['sends']} sends")
            return
        if cmd["last_sent_at"] is not None and now - cmd["last_sent_at"] < (
            self.settings.resend_interval_s
        ):
            return
        if now - track.last_attempt < self.settings.resend_interval_s:
            return  # the bus was down a moment ago: do not hammer it
        if cmd["sends"] >= cmd["max_sends"]:
            if cmd["kind"] == "parameters":
                await self._finish(
                    cmd,
                    "sent",
                    f"sent {cmd['sends']} times; parameter writes have no read-back: "
                    "sent, not confirmable",
                )
            else:
                await self._finish(
                    cmd, "failed", f"no answer from the unit after {cmd['sends']} requests"
                )
            return
        writer = self.writers.get(cmd["bus"])
        if writer is None and self._routable is not None and self._routable(cmd["bus"]):
            self._pending.pop(cmd["id"], None)  # another gateway owns the bus now
            self._tracking.pop(cmd["id"], None)
            return
        if writer is None:
            await self._finish(cmd, "failed", f"no transmit path on bus {cmd['bus']!r}")
            return
        try:
            frames = self._frames(cmd, writer)
        except (EncodeError, ValueError) as exc:
            await self._finish(cmd, "failed", f"cannot encode: {exc}")
            return
        track.last_attempt = now
        if cmd["sends"] == 0:
            track.baseline_ts = self._baseline(cmd)
        try:
            for can_id, data in frames:
                # Re-check right before each frame: a command that expired, or ended (was
                # cancelled) while this round waited on another command's send, never
                # reaches the bus. The send itself gives up at the expiry.
                if time.time() >= cmd["expires_at"] or not self._live(cmd):
                    return
                await writer.send(can_id, data, deadline=cmd["expires_at"])
                self.frames_sent += 1
        except BusError as exc:
            track.last_bus_error = str(exc)
            return
        sent_at = time.time()
        values = {
            "sends": cmd["sends"] + 1,
            "last_sent_at": sent_at,
            "updated_at": sent_at,
            "state": "sending",
            "first_sent_at": cmd["first_sent_at"] or sent_at,
        }
        if await self._db(q.update_command, cmd["id"], values):
            first = cmd["sends"] == 0
            cmd.update(values)
            if first:
                self._publish(cmd)
        else:
            self._pending.pop(cmd["id"], None)  # ended elsewhere (cancelled)

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
            q.add_audit,
            {
                "ts": now,
                "key_id": cmd["key_id"],
                "key_name": cmd["key_name"],
                "role": None,
                "action": f"command.{cmd['kind']}.{state}",
                "vehicle_id": cmd["vehicle_id"],
                "target": f"{cmd['bus']}/{cmd['sa']}",
                "request": None,
                "outcome": state,
                "status_code": 200,
                "detail": reason,
                "command_id": cmd["id"],
            },
        )

    async def _finish_by_id(self, command_id: str, state: str, reason: str) -> bool:
        cmd = self._pending.get(command_id)
        if cmd is None:
            row = await self._db(q.get_command, command_id)
            if row is None or row["state"] not in q.PENDING_STATES:
                return False
            cmd = row
        before = cmd["state"]
        await self._finish(cmd, state, reason)
        return bool(cmd["state"] == state and before != state)

    def _publish(self, cmd: Mapping[str, Any]) -> None:
        ref = UnitRef(cmd["vehicle_id"], cmd["bus"], cmd["sa"])
        self.hub.publish(Event(COMMAND_EVENT, ref, time.time(), public_command(cmd)))


def public_command(cmd: Mapping[str, Any]) -> dict[str, Any]:
    """A command as the API shows it."""
    p = cmd["payload"]
    return {
        "id": cmd["id"],
        "kind": cmd["kind"],
        "vehicle_id": cmd["vehicle_id"],
        "bus": cmd["bus"],
        "unit": cmd["sa"],
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
