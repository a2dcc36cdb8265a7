"""A command's life, pure: from the facts of a delivery step, what happens next.

Nothing here touches the bus, the database, the live state or the clock: the delivery loop
(`eqgw.commands.delivery`) gathers the facts and applies what is decided. The rules:

- `step` looks at a pending command: confirmed (every unit reached showed it since the first
  send), refused (a unit NACKed it), expired, not due yet, out of sends, or due for a send.
- `route` decides whether a due send goes out here, is left to the gateway that owns the bus,
  or ends the command because nothing can transmit it.
- `after_round` decides what a delivery round that handed over all, some or none of its
  frames leaves recorded.
- `ending` decides how a command ends from what its row shows when it ends (read under a
  lock), for every cause: expiry, no transmit path, a cancel, a bus nobody delivers on. A
  command whose row records a hand-over (`handed_at`) never ends `expired` or `failed`,
  and a cancel says what was sent: once a frame may have left, nothing reports it unsent.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from datetime import UTC, datetime
from enum import Enum

from eqgw.commands.model import CommandChanges, CommandKind, CommandState
from eqgw.jsontypes import JSONObject
from eqgw.protocol.acknowledgement import REFUSALS, concerns, describe_answer

# A unit's latest record in a live slot: (time received, decoded fields).
Answer = tuple[float, JSONObject]


# -- ending a command from its row --------------------------------------------------------


@dataclass(frozen=True, slots=True)
class Record:
    """What a command's row shows of its hand-over, read when the command ends."""

    kind: CommandKind
    # Written before the first frame goes to an interface: set, something may have left.
    handed_at: float | None
    sends: int  # complete sends recorded
    frames_handed: int  # frames of sends that did not complete


@dataclass(frozen=True, slots=True)
class Expiry:
    """The command reached its expiry while pending."""

    last_bus_error: str | None = None


@dataclass(frozen=True, slots=True)
class Undeliverable:
    """It cannot be sent (again): no transmit path on its bus, or it cannot be encoded."""

    reason: str


@dataclass(frozen=True, slots=True)
class Cancel:
    """Cancelled through the API by the key named."""

    by: str | None


@dataclass(frozen=True, slots=True)
class Abandoned:
    """Past its expiry (and a grace) on a bus no running gateway delivers on."""

    bus: str


EndCause = Expiry | Undeliverable | Cancel | Abandoned


@dataclass(frozen=True, slots=True)
class Ending:
    """A final state and its reason."""

    state: CommandState
    reason: str


def ending(cause: EndCause, record: Record) -> Ending:
    """How a command ends for `cause`, from its row as it is when it ends: as unsent only
    when nothing of it was ever handed over."""
    if record.handed_at is None:
        return _ending_unsent(cause)
    return _ending_handed(cause, record)


def _ending_unsent(cause: EndCause) -> Ending:
    """The ending of a command nothing of which was ever handed over."""
    match cause:
        case Expiry(error):
            return Ending(
                CommandState.EXPIRED,
                f"expired before it could be sent{f': {error}' if error else ''}",
            )
        case Undeliverable(reason):
            return Ending(CommandState.FAILED, reason)
        case Cancel(key_name):
            return Ending(CommandState.CANCELLED, f"cancelled by {key_name}")
        case Abandoned(bus):
            return Ending(
                CommandState.EXPIRED,
                f"expired before it could be sent: no gateway delivered on {bus}",
            )


def _ending_handed(cause: EndCause, record: Record) -> Ending:
    """The ending of a command handed over (`handed_at` set): never `expired` or `failed`,
    and the reason says what was sent."""
    match cause:
        case Expiry(error):
            return Ending(CommandState.UNCONFIRMED, unconfirmed_reason(record, error))
        case Undeliverable(reason):
            return Ending(
                CommandState.UNCONFIRMED,
                f"{reason}; {what_left(record)} before, not confirmed: it may still take effect",
            )
        case Cancel(key_name):
            return Ending(
                CommandState.CANCELLED,
                f"cancelled by {key_name} after it was {what_left(record)}: "
                "what was sent may still take effect",
            )
        case Abandoned(bus):
            return Ending(
                CommandState.UNCONFIRMED,
                f"{what_left(record)}, then no gateway delivered on {bus} before expiry; "
                "it may still take effect",
            )


def what_left(record: Record) -> str:
    """What of a command handed over (`handed_at` set) the record shows."""
    sends, partly = record.sends, record.frames_handed
    parts = [f"sent {sends} time{'s' if sends != 1 else ''}"] if sends else []
    if partly:
        parts.append(f"{partly} frame{'s' if partly != 1 else ''} of an unfinished send")
    if not parts:
        assert record.handed_at is not None
        begun = datetime.fromtimestamp(record.handed_at, UTC).isoformat(timespec="milliseconds")
        parts.append(
            f"a send begun at {begun} whose outcome was not recorded (its gateway stopped or "
            "its database failed right after)"
        )
    return " and ".join(parts)


def unconfirmed_reason(record: Record, last_bus_error: str | None) -> str:
    """Why a command handed over ends `unconfirmed` at its expiry."""
    if record.kind == CommandKind.CONTROL:
        check = "not confirmed by the status flags before expiry"
    elif record.kind == CommandKind.REQUEST:
        check = "no answer from the unit before expiry"
    else:
        check = "expired before all sends (parameter writes have no read-back)"
    why = f" (last bus error: {last_bus_error})" if last_bus_error else ""
    return f"{what_left(record)}, {check}; it may still take effect{why}"


# -- a delivery step ----------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class Situation:
    """The facts of a pending command at a delivery step."""

    kind: CommandKind
    now: float
    expires_at: float
    sends: int
    max_sends: int
    last_sent_at: float | None  # the last complete send
    last_attempt: float  # the last round begun in this process (-inf: none)
    resend_interval_s: float
    # Every unit reached has shown it since the first send (see `confirmed`).
    confirmed: bool = False
    # A unit reached refused it since the first send (see `refusal`), with its answer.
    refusal: str | None = None
    last_bus_error: str | None = None


@dataclass(frozen=True, slots=True)
class Wait:
    """Nothing to do now."""


@dataclass(frozen=True, slots=True)
class Finish:
    """End the command now in `state` (if it is still pending)."""

    state: CommandState
    reason: str


@dataclass(frozen=True, slots=True)
class End:
    """End the command as `ending(cause, its row)` says, from its row locked as it is now."""

    cause: EndCause


@dataclass(frozen=True, slots=True)
class Due:
    """A send is due: see `route`."""


Step = Wait | Finish | End | Due


def step(s: Situation) -> Step:
    """What a delivery step does with a pending command."""
    if s.sends and s.confirmed:
        reason = (
            "confirmed by the status flags"
            if s.kind == CommandKind.CONTROL
            else "the unit answered"
        )
        return Finish(CommandState.CONFIRMED, reason)
    if s.refusal is not None:
        return Finish(CommandState.REFUSED, s.refusal)
    if s.now >= s.expires_at:
        return End(Expiry(s.last_bus_error))
    if s.last_sent_at is not None and s.now - s.last_sent_at < s.resend_interval_s:
        return Wait()
    if s.now - s.last_attempt < s.resend_interval_s:
        return Wait()  # the bus was down a moment ago: do not hammer it
    if s.sends >= s.max_sends:
        return _out_of_sends(s.kind, s.sends)
    return Due()


def _out_of_sends(kind: CommandKind, sends: int) -> Finish:
    """A command sent as many times as it may be, never confirmed."""
    if kind == CommandKind.PARAMETERS:
        return Finish(
            CommandState.SENT,
            f"sent {sends} times; parameter writes have no read-back: sent, not confirmable",
        )
    return Finish(
        CommandState.UNCONFIRMED,
        f"sent {sends} times, no answer from the unit; it may still take effect",
    )


class Path(Enum):
    """Who can transmit on a command's bus."""

    OWN = "own"  # this process
    ELSEWHERE = "elsewhere"  # another gateway on the database (it owns the bus now)
    NONE = "none"  # no gateway


@dataclass(frozen=True, slots=True)
class Send:
    """Hand the command's frames over here."""


@dataclass(frozen=True, slots=True)
class Release:
    """Stop delivering it here: the gateway that owns its bus does (the row stays queued)."""


def route(path: Path, bus: str) -> Send | Release | End:
    """Where a due send goes."""
    if path is Path.OWN:
        return Send()
    if path is Path.ELSEWHERE:
        return Release()
    return End(Undeliverable(f"no transmit path on bus {bus!r}"))


def unencodable(error: str) -> End:
    """A command whose frames cannot be built."""
    return End(Undeliverable(f"cannot encode: {error}"))


def hand_over_mark(handed_at: float | None, now: float) -> CommandChanges:
    """Written to the row, only while the command is pending, before a round hands anything
    over: from then on nothing reports the command as unsent."""
    return {"state": CommandState.SENDING, "handed_at": handed_at or now}


def may_hand(now: float, expires_at: float, pending: bool) -> bool:
    """Whether the next frame of a round may go: the command is still pending here and has
    not expired (a round can wait on another command's send)."""
    return now < expires_at and pending


class RoundOutcome(Enum):
    """What a delivery round leaves recorded."""

    COMPLETE = "complete"  # every frame handed over: a send
    PARTIAL = "partial"  # some frames: counted in `frames_handed`, not a send
    TAKE_BACK = "take_back"  # none, and none ever before: the hand-over mark is taken back
    KEEP = "keep"  # none this round, but earlier rounds handed frames over: the mark stays


def after_round(frames: int, handed: int, handed_before: bool) -> RoundOutcome:
    """`handed` of a round's `frames` went to the interface (a send that failed after the
    interface may have taken its frame counts it); `handed_before`: the row recorded a
    hand-over before this round."""
    if handed >= frames:
        return RoundOutcome.COMPLETE
    if handed:
        return RoundOutcome.PARTIAL
    if not handed_before:
        return RoundOutcome.TAKE_BACK
    return RoundOutcome.KEEP


def record_send(sends: int, first_sent_at: float | None, sent_at: float) -> CommandChanges:
    """A complete send, as the row records it."""
    return {
        "sends": sends + 1,
        "last_sent_at": sent_at,
        "updated_at": sent_at,
        "state": CommandState.SENDING,
        "first_sent_at": first_sent_at or sent_at,
    }


# -- what the units answered --------------------------------------------------------------


def confirmed(
    kind: CommandKind,
    first_sent_at: float | None,
    expect: Mapping[str, str],
    answers: Sequence[tuple[int, Answer | None]] | None,
    baselines: Mapping[int, float | None],
) -> bool:
    """Whether every unit reached has answered since the first send: for control, a status
    frame of each showing every flag wanted (`expect`); for a request, the answer.

    `answers`: per unit reached, its latest record in the command's answer slot (None: the
    command has no slot); `baselines`: when that record was, per unit, before the first send
    (only records after it count)."""
    if first_sent_at is None or answers is None:
        return False
    for sa, latest in answers:
        if latest is None:
            return False
        ts, fields = latest
        baseline = baselines.get(sa)
        if baseline is not None and ts <= baseline:
            return False
        if kind == CommandKind.CONTROL and not all(
            fields.get(flag) == want for flag, want in expect.items()
        ):
            return False
    return True


def refusal(
    handed_at: float | None,
    answers: Sequence[tuple[int, Answer | None]],
    baselines: Mapping[int, float | None],
    pgn: int,
    gateway_sa: int,
) -> str | None:
    """The reason to end a command as refused: a unit it reaches answered it, after the first
    hand-over, with a NACK or "access denied" (J1939-21 Acknowledgement, PGN 59392) naming
    `pgn` and the gateway; else None. "Cannot respond" (busy) does not end it.

    `answers`: per unit reached, its latest acknowledgement; `baselines`: the time of each
    unit's latest one before the first send."""
    if handed_at is None:
        return None
    for sa, latest in answers:
        if latest is None:
            continue
        ts, fields = latest
        baseline = baselines.get(sa)
        if baseline is not None and ts <= baseline:
            continue  # an answer to something sent before this command
        if fields.get("control") in REFUSALS and concerns(fields, pgn, gateway_sa):
            return f"refused by unit {sa}: {describe_answer(fields)}"
    return None
