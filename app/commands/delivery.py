"""Delivery: hand pending commands to the bus, repeat them, confirm them, end them.

The loop gathers the facts of each pending command (its row, the live state, the bus) and does
what `eqgw.commands.lifecycle` decides. A mixin of `CommandService`: the state it reads is
declared on `Delivery` and set by `CommandService.__init__`.
"""

from __future__ import annotations

import asyncio
import contextlib
import copy
import logging
import math
import time
from collections import Counter
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import Concatenate

from sqlalchemy import Connection, Engine

from eqgw.bus.config import BusConfig
from eqgw.bus.errors import BusError, BusSendError
from eqgw.bus.writer import BusWriter
from eqgw.commands import lifecycle as life
from eqgw.commands import repository as q
from eqgw.commands.model import (
    FINAL_STATES,
    Command,
    CommandChanges,
    CommandKind,
    CommandState,
    command_pgn,
    command_target,
    command_units,
    public_command,
)
from eqgw.describe import describe
from eqgw.ingest.events import Event, UnitRef
from eqgw.ingest.hub import EventHub
from eqgw.ingest.state import LiveState
from eqgw.protocol.encode import Frame, encode
from eqgw.protocol.errors import EncodeError
from eqgw.protocol.j1939 import DEFAULT_GATEWAY_SA
from eqgw.protocol.params import encode_parameter_write
from eqgw.security import repository as security_q
from eqgw.store.transaction import P, R, run_in_transaction
from eqgw.tasks import Backoff, heals
from eqgw.web.settings import ApiSettings

log = logging.getLogger(__name__)


COMMAND_EVENT = "command"

# How long past its expiry a never-sent command for a bus this gateway does not deliver on
# waits before this gateway ends it (the owner, if there is one, ends it first).
UNOWNED_EXPIRY_GRACE_S = 5.0
# After a failed delivery round (the database away): the next from 0.5 s, doubling up to 5 s.
ROUND_RETRY_S, ROUND_RETRY_MAX_S = 0.5, 5.0

# The live slot of a unit's latest Acknowledgement (PGN 59392) record.
ACK_SLOT = "acknowledgement"


@dataclass(slots=True)
class _Tracking:
    """In-memory delivery state of a pending command (baselines for confirmation)."""

    # Per unit reached: the time of its latest answer slot (status) before the first send.
    baselines: dict[int, float | None] = field(default_factory=dict)
    # Per unit reached: the time of its latest acknowledgement (PGN 59392) before the first send.
    ack_baselines: dict[int, float | None] = field(default_factory=dict)
    last_bus_error: str | None = None
    last_attempt: float = field(default=-math.inf)


class Delivery:
    """Delivers the commands of the buses this process owns (see the module)."""

    engine: Engine
    _serial_engine: Engine
    live: LiveState
    writers: dict[str, BusWriter]
    buses: dict[str, BusConfig]
    settings: ApiSettings
    hub: EventHub
    outcomes: Counter[tuple[str, str]]
    frames_sent: int
    _routable: Callable[[str], bool] | None
    _pending: dict[str, Command]
    _submitting: set[str]
    _tracking: dict[str, _Tracking]
    _wake: asyncio.Event
    _reload_now: bool

    async def _db(
        self, fn: Callable[Concatenate[Connection, P], R], /, *args: P.args, **kwargs: P.kwargs
    ) -> R:
        return await run_in_transaction(self.engine, fn, *args, **kwargs)

    async def _db_serialized(
        self, fn: Callable[Concatenate[Connection, P], R], /, *args: P.args, **kwargs: P.kwargs
    ) -> R:
        """Run `fn(conn, *args)` in a transaction that, on SQLite, holds the write lock from
        its start (so what it reads cannot change before it writes)."""

        def run() -> R:
            with self._serial_engine.begin() as conn:
                return fn(conn, *args, **kwargs)

        return await asyncio.to_thread(run)

    # -- delivery -----------------------------------------------------------------------------

    async def _reload(self) -> None:
        self._reload_now = False
        buses = list(self.writers)
        rows: list[Command] = await self._db(q.pending_commands, buses)
        # Ended by another process (cancelled through an API-only instance): stop sending.
        # Only a row read as ended counts (one just submitted here may postdate the query).
        still = {row.id for row in rows}
        missing = [
            cid for cid, cmd in self._pending.items() if cid not in still and cmd.bus in buses
        ]
        ended = await self._db(q.ended_commands, missing) if missing else {}
        for cid, final in ended.items():
            gone = self._pending.pop(cid, None)
            self._tracking.pop(cid, None)
            if gone is not None:
                gone.apply(final)
        for row in rows:
            # The bus not given up while the query ran; the row not one being submitted here.
            if row.bus in self.writers and row.id not in self._submitting:
                self._pending.setdefault(row.id, row)
        # Commands for buses nobody here delivers on, never sent and past their expiry: the
        # owner would end them, but there may be none (its gateway down, the bus unreachable).
        # A grace past the expiry: an owner's send just before it may not be recorded yet.
        now = time.time()
        before = now - UNOWNED_EXPIRY_GRACE_S
        for cmd in await self._db_serialized(_end_unowned, buses, before, _abandoned, now):
            self._ended(cmd)

    async def _run(self) -> None:
        last_reload = time.monotonic()
        backoff = Backoff(ROUND_RETRY_S, ROUND_RETRY_MAX_S)
        wait = self.settings.delivery_poll_s
        while True:
            await self._until_woken(wait)
            try:
                last_reload = await self._pass(last_reload)
            except Exception as exc:  # the database may be away: retry after a backoff
                if not heals(exc):
                    raise  # a bug or storage gone for good: its supervisor says so
                # The retry asks the database again (a pass that skips it, the queue reloaded
                # moments before, would pass for the database being back).
                self._reload_now = True
                wait = backoff.next()
                _failed_round(backoff.failures, exc)
            else:
                if backoff.failures:
                    log.warning("command delivery resumed after %d failed rounds", backoff.failures)
                backoff.reset()
                wait = self.settings.delivery_poll_s

    async def _until_woken(self, wait: float) -> None:
        """Wait for a poke or `wait` seconds (the next poll; after a failed round, the
        backoff's delay)."""
        with contextlib.suppress(TimeoutError):
            async with asyncio.timeout(wait):
                await self._wake.wait()
        self._wake.clear()

    async def _pass(self, last_reload: float) -> float:
        """One pass of the loop: reload the queue when due or asked to, then step every pending
        command. Returns when the queue was last reloaded (time.monotonic())."""
        if self._reload_now or time.monotonic() - last_reload >= 1.0:
            # Commands queued by another process (e.g. an API-only instance).
            await self._reload()
            last_reload = time.monotonic()
        for cmd in list(self._pending.values()):
            await self._step(cmd)
        return last_reload

    def _answers(self, cmd: Command, slot: str) -> list[tuple[int, life.Answer | None]]:
        """Per unit the command reaches, its latest record in the live `slot`."""
        out: list[tuple[int, life.Answer | None]] = []
        for sa in command_units(cmd):
            st = self.live.get(cmd.bus, sa)
            out.append((sa, st.latest.get(slot) if st is not None else None))
        return out

    def _confirmed(self, cmd: Command, track: _Tracking) -> bool:
        """Whether every unit the command reaches has answered since the first send
        (`lifecycle.confirmed`)."""
        p = cmd.payload
        slot = "status" if cmd.kind == CommandKind.CONTROL else p.get("slot")
        answers = None if slot is None else self._answers(cmd, slot)
        return life.confirmed(
            cmd.kind, cmd.first_sent_at, p.get("expect", {}), answers, track.baselines
        )

    def _series(self, cmd: Command) -> int | None:
        """The series of every unit the command reaches if they share one, else None (then
        only what both series accept is encoded, as validation allowed)."""
        found = set()
        for sa in command_units(cmd):
            st = self.live.get(cmd.bus, sa)
            found.add(st.series if st is not None else None)
        return found.pop() if len(found) == 1 else None

    def _frames(self, cmd: Command, writer: BusWriter) -> list[Frame]:
        p = cmd.payload
        series = self._series(cmd)
        gw = writer.gateway_sa
        if cmd.kind == CommandKind.CONTROL:
            return encode("control", p["fields"], sa=gw, series=series or 80)
        if cmd.kind == CommandKind.PARAMETERS:
            return encode_parameter_write(p["values"], sa=gw, series=series, da=cmd.sa)
        order = self.buses[cmd.bus].request_byte_order if cmd.bus in self.buses else "lsb"
        return encode(
            "request",
            {"requested_pgn": p["pgn"], "da": cmd.sa},
            sa=gw,
            request_byte_order=order,
        )

    def _refusal(self, cmd: Command, track: _Tracking) -> str | None:
        """Why to end a command as refused: a unit it reaches answered it with a NACK or
        "access denied" (`lifecycle.refusal`); else None."""
        if cmd.handed_at is None:
            return None
        bus = self.buses.get(cmd.bus)
        writer = self.writers.get(cmd.bus)
        gateway = bus.gateway_sa if bus else writer.gateway_sa if writer else DEFAULT_GATEWAY_SA
        return life.refusal(
            cmd.handed_at,
            self._answers(cmd, ACK_SLOT),
            track.ack_baselines,
            command_pgn(cmd),
            gateway,
        )

    def _baselines(self, cmd: Command, slot: str | None = None) -> dict[int, float | None]:
        """Per unit reached, when its latest answer slot (or `slot`) arrived (before the
        first send)."""
        if slot is None:
            slot = "status" if cmd.kind == CommandKind.CONTROL else cmd.payload.get("slot")
        out: dict[int, float | None] = {}
        for sa in command_units(cmd):
            st = self.live.get(cmd.bus, sa)
            latest = st.latest.get(slot) if st is not None and slot is not None else None
            out[sa] = latest[0] if latest else None
        return out

    def _live(self, cmd: Command) -> bool:
        """Whether a command is still this process's to deliver (not ended meanwhile)."""
        return cmd.state not in FINAL_STATES and self._pending.get(cmd.id) is cmd

    async def _step(self, cmd: Command) -> None:
        """One delivery step of a pending command: gather the facts, let the lifecycle
        decide, do what it decided."""
        if not self._live(cmd):
            return  # ended (cancelled) earlier in this round
        track = self._tracking.setdefault(cmd.id, _Tracking())
        now = time.time()
        decision: life.Step | life.Send | life.Release = life.step(
            life.Situation(
                kind=cmd.kind,
                now=now,
                expires_at=cmd.expires_at,
                sends=cmd.sends,
                max_sends=cmd.max_sends,
                last_sent_at=cmd.last_sent_at,
                last_attempt=track.last_attempt,
                resend_interval_s=self.settings.resend_interval_s,
                confirmed=self._confirmed(cmd, track),
                refusal=self._refusal(cmd, track),
                last_bus_error=track.last_bus_error,
            )
        )
        if isinstance(decision, life.Due):
            decision = life.route(self._path(cmd.bus), cmd.bus)
        match decision:
            case life.Finish(state, reason):
                await self._finish(cmd, state, reason)
            case life.End(cause):
                await self._end(cmd.id, cause)
            case life.Release():
                self._release(cmd.id)  # another gateway owns the bus now
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

    async def _round(self, cmd: Command, track: _Tracking, now: float) -> None:
        """A delivery round: record the hand-over ahead, hand every frame to the interface,
        record what went."""
        writer = self.writers[cmd.bus]
        try:
            frames = self._frames(cmd, writer)
        except (EncodeError, ValueError) as exc:
            await self._end(cmd.id, life.unencodable(str(exc)).cause)
            return
        track.last_attempt = now
        if cmd.sends == 0:
            track.baselines = self._baselines(cmd)
            track.ack_baselines = self._baselines(cmd, ACK_SLOT)
        # Written ahead of the hand-over, and only while the command is pending: once it is
        # recorded nothing reports the command as unsent (a death or a failed record right
        # after a frame left included), and a command ended meanwhile (cancelled through
        # another process) is never handed over again.
        before: CommandChanges = {"state": cmd.state, "handed_at": cmd.handed_at}
        ahead = life.hand_over_mark(cmd.handed_at, now)
        if not await self._db(q.update_command, cmd.id, ahead):
            self._release(cmd.id)  # ended elsewhere
            return
        cmd.apply(ahead)
        handed = await self._hand_over(cmd, track, writer, frames)
        outcome = life.after_round(len(frames), handed, before.get("handed_at") is not None)
        await self._record_round(cmd, outcome, handed, before)

    async def _record_round(
        self, cmd: Command, outcome: life.RoundOutcome, handed: int, before: CommandChanges
    ) -> None:
        """Record what a delivery round handed over, as `lifecycle.after_round` decided."""
        if outcome is life.RoundOutcome.PARTIAL:
            # An incomplete round is not a send; what of it may have left is counted.
            cmd.frames_handed += handed
            await self._db(q.add_frames_handed, cmd.id, handed)
        elif outcome is life.RoundOutcome.TAKE_BACK:
            # Provably nothing handed over (the bus refused every frame before the
            # hand-over, or the command ended first): as unsent as before the round.
            if await self._db(q.update_command, cmd.id, before):
                cmd.apply(before)
        elif outcome is life.RoundOutcome.COMPLETE:
            values = life.record_send(cmd.sends, cmd.first_sent_at, time.time())
            if await self._db(q.update_command, cmd.id, values):
                first = cmd.sends == 0
                cmd.apply(values)
                if first:
                    self._publish(cmd)
            else:
                self._pending.pop(cmd.id, None)  # ended elsewhere (cancelled)

    async def _hand_over(
        self, cmd: Command, track: _Tracking, writer: BusWriter, frames: list[Frame]
    ) -> int:
        """Hand a round's frames to the interface; how many went (a send that failed after
        the interface may have taken its frame counts it)."""
        handed = 0
        try:
            for can_id, data in frames:
                # Re-check right before each frame: a command that expired, or ended (was
                # cancelled) while this round waited on another command's send, never
                # reaches the bus. The send itself gives up at the expiry.
                if not life.may_hand(time.time(), cmd.expires_at, self._live(cmd)):
                    break
                await writer.send(can_id, data, deadline=cmd.expires_at)
                handed += 1
                self.frames_sent += 1
        except BusError as exc:
            track.last_bus_error = str(exc)
            if isinstance(exc, BusSendError) and exc.handed:
                handed += 1
        return handed

    async def _finish(self, cmd: Command, state: CommandState, reason: str) -> None:
        now = time.time()
        values: CommandChanges = {"state": state, "reason": reason, "updated_at": now}
        if await self._db(_finish_command, cmd, values):
            cmd.apply(values)
            self._ended(cmd)
        self._pending.pop(cmd.id, None)
        self._tracking.pop(cmd.id, None)

    def _ended(self, cmd: Command) -> None:
        """Count and publish a command that just reached its final state (its row and its
        audit entry committed together)."""
        self.outcomes[(cmd.kind.value, cmd.state.value)] += 1
        self._publish(cmd)

    async def _end(self, command_id: str, cause: life.EndCause) -> Command | None:
        """End a pending command as the lifecycle decides for `cause` from its row locked as
        it is now (so a hand-over recorded by a delivery round is seen); the ended command,
        or None when it was no longer pending."""
        now = time.time()
        row = await self._db_serialized(_end_command, command_id, _decide(cause), now)
        cmd = self._pending.pop(command_id, None)
        self._tracking.pop(command_id, None)
        if row is None:
            return None
        if cmd is None:
            cmd = row
        else:
            cmd.refresh(row)
        self._ended(cmd)
        return cmd

    def _publish(self, cmd: Command) -> None:
        ref = UnitRef(cmd.vehicle_id, cmd.bus, cmd.sa)
        self.hub.publish(Event(COMMAND_EVENT, ref, time.time(), public_command(cmd)))


# A command's end state and its audit entry are written in one transaction: what the
# command shows ended is in the audit trail too, even when the process stops right after.


def _audit_end(conn: Connection, cmd: Command, now: float) -> None:
    """The audit entry of a command that reached its final state (`cmd` shows it)."""
    security_q.add_audit(
        conn,
        {
            "ts": now,
            "key_id": cmd.key_id,
            "key_name": cmd.key_name,
            "role": None,
            "action": f"command.{cmd.kind}.{cmd.state}",
            "vehicle_id": cmd.vehicle_id,
            "target": command_target(cmd),
            "request": None,
            "outcome": cmd.state.value,
            "status_code": 200,
            "detail": cmd.reason,
            "command_id": cmd.id,
        },
    )


def _finish_command(conn: Connection, cmd: Command, values: CommandChanges) -> bool:
    """End a pending command with `values` (its final state) and audit it; False when it had
    already ended (nothing written)."""
    if not q.update_command(conn, cmd.id, values):
        return False
    ended = copy.copy(cmd)
    ended.apply(values)
    _audit_end(conn, ended, values["updated_at"])
    return True


def _end_command(conn: Connection, command_id: str, decide: q.Decide, now: float) -> Command | None:
    """`q.end_command`, audited."""
    cmd = q.end_command(conn, command_id, decide, now)
    if cmd is not None:
        _audit_end(conn, cmd, now)
    return cmd


def _end_unowned(
    conn: Connection, skip_buses: Iterable[str], before: float, decide: q.Decide, now: float
) -> list[Command]:
    """`q.end_unowned`, each command audited."""
    ended = q.end_unowned(conn, skip_buses, before, decide, now)
    for cmd in ended:
        _audit_end(conn, cmd, now)
    return ended


def _record(row: Command) -> life.Record:
    """What a command's row shows of its hand-over."""
    return life.Record(row.kind, row.handed_at, row.sends, row.frames_handed)


def _decide(cause: life.EndCause) -> q.Decide:
    """How a command ends for `cause`, decided from its row when it ends."""

    def decide(row: Command) -> tuple[CommandState, str]:
        end = life.ending(cause, _record(row))
        return end.state, end.reason

    return decide


def _abandoned(row: Command) -> tuple[CommandState, str]:
    """How a command past its expiry on a bus no running gateway delivers on ends."""
    return _decide(life.Abandoned(row.bus))(row)


def _failed_round(failures: int, exc: Exception) -> None:
    """Log a failed delivery round (called while `exc` is handled): the first failure with its
    traceback, then one line every 10 in a row."""
    if failures == 1:
        log.exception("command delivery round failed; retrying")
    elif failures % 10 == 0:
        log.warning("command delivery rounds failing (%d in a row): %s", failures, describe(exc))
