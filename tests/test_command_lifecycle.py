"""The command lifecycle's decisions, as a table (eqgw.commands.lifecycle is pure: no bus, no
database, no clock), plus properties over every record and situation."""

# ruff: noqa: E501  (the tables keep one transition a line)

from __future__ import annotations

import math
from dataclasses import replace

import pytest
from hypothesis import given
from hypothesis import strategies as st

from eqgw.commands.lifecycle import (
    Abandoned,
    Cancel,
    Due,
    End,
    EndCause,
    Ending,
    Expiry,
    Finish,
    Path,
    Record,
    Release,
    RoundOutcome,
    Send,
    Situation,
    Undeliverable,
    Wait,
    after_round,
    confirmed,
    ending,
    hand_over_mark,
    may_hand,
    record_send,
    refusal,
    route,
    step,
    unencodable,
)
from eqgw.commands.model import CommandKind, CommandState
from eqgw.protocol.j1939 import PGN_CONTROL, PGN_PARAMETERS

CONTROL, PARAMETERS, REQUEST = CommandKind.CONTROL, CommandKind.PARAMETERS, CommandKind.REQUEST
S = CommandState
T0 = 1_795_440_000.0  # 2026-11-23 13:20:00 UTC
BEGUN = "2026-11-23T13:20:00.000+00:00"

# A pending control command, due for its second send.
DUE = Situation(
    kind=CONTROL,
    now=T0 + 10,
    expires_at=T0 + 30,
    sends=1,
    max_sends=1_000_000,
    last_sent_at=T0 + 8,
    last_attempt=T0 + 8,
    resend_interval_s=1.0,
)


# -- step ---------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("situation", "decision"),
    [
        pytest.param(DUE, Due(), id="due"),
        pytest.param(replace(DUE, confirmed=True), Finish(S.CONFIRMED, "confirmed by the status flags"), id="control-confirmed"),
        pytest.param(replace(DUE, kind=REQUEST, max_sends=3, confirmed=True), Finish(S.CONFIRMED, "the unit answered"), id="request-answered"),
        # Confirmation counts only once something was sent.
        pytest.param(replace(DUE, sends=0, last_sent_at=None, confirmed=True), Due(), id="confirmed-before-any-send"),
        # Confirmation wins over a refusal and over the expiry.
        pytest.param(replace(DUE, confirmed=True, refusal="refused by unit 30: NACK", now=T0 + 40), Finish(S.CONFIRMED, "confirmed by the status flags"), id="confirmed-beats-refusal-and-expiry"),
        pytest.param(replace(DUE, refusal="refused by unit 30: NACK for PGN 65490 (0xFFD2)"), Finish(S.REFUSED, "refused by unit 30: NACK for PGN 65490 (0xFFD2)"), id="refused"),
        pytest.param(replace(DUE, refusal="refused by unit 31: access denied", now=T0 + 40), Finish(S.REFUSED, "refused by unit 31: access denied"), id="refusal-beats-expiry"),
        pytest.param(replace(DUE, now=T0 + 30), End(Expiry()), id="expired-at-expiry"),
        pytest.param(replace(DUE, now=T0 + 30, last_bus_error="bus down"), End(Expiry("bus down")), id="expired-with-bus-error"),
        # Past its expiry a command never gets another send, whatever else holds.
        pytest.param(replace(DUE, now=T0 + 31, sends=3, max_sends=3, kind=PARAMETERS), End(Expiry()), id="expiry-beats-out-of-sends"),
        pytest.param(replace(DUE, now=T0 + 8.5), Wait(), id="resend-not-due"),
        pytest.param(replace(DUE, last_sent_at=T0 + 5, last_attempt=T0 + 9.5), Wait(), id="bus-down-a-moment-ago"),
        pytest.param(replace(DUE, sends=0, last_sent_at=None, last_attempt=-math.inf), Due(), id="first-send"),
        pytest.param(replace(DUE, kind=PARAMETERS, sends=3, max_sends=3), Finish(S.SENT, "sent 3 times; parameter writes have no read-back: sent, not confirmable"), id="parameters-all-sent"),
        pytest.param(replace(DUE, kind=REQUEST, sends=3, max_sends=3), Finish(S.UNCONFIRMED, "sent 3 times, no answer from the unit; it may still take effect"), id="request-unanswered"),
        pytest.param(replace(DUE, kind=PARAMETERS, sends=2, max_sends=3), Due(), id="parameters-one-more"),
        # Out of sends is decided only when a send would be due.
        pytest.param(replace(DUE, kind=PARAMETERS, sends=3, max_sends=3, now=T0 + 8.5), Wait(), id="out-of-sends-waits-for-the-interval"),
    ],
)  # fmt: skip
def test_step(situation: Situation, decision: object) -> None:
    assert step(situation) == decision


situations = st.builds(
    Situation,
    kind=st.sampled_from(CommandKind),
    now=st.floats(T0, T0 + 100),
    expires_at=st.floats(T0, T0 + 100),
    sends=st.integers(0, 5),
    max_sends=st.integers(1, 5),
    last_sent_at=st.none() | st.floats(T0 - 10, T0 + 100),
    last_attempt=st.just(-math.inf) | st.floats(T0 - 10, T0 + 100),
    resend_interval_s=st.floats(0.1, 5),
    confirmed=st.booleans(),
    refusal=st.none() | st.just("refused by unit 30: NACK"),
    last_bus_error=st.none() | st.just("bus down"),
)


@given(situations)
def test_nothing_is_sent_at_or_past_the_expiry(s: Situation) -> None:
    decision = step(s)
    if s.now >= s.expires_at:
        assert not isinstance(decision, Due | Wait)
        if not (s.sends and s.confirmed) and s.refusal is None:
            assert decision == End(Expiry(s.last_bus_error))


@given(situations)
def test_a_step_ends_a_command_only_with_a_final_state(s: Situation) -> None:
    decision = step(s)
    if isinstance(decision, Finish):
        assert decision.state not in (S.QUEUED, S.SENDING, S.FAILED, S.EXPIRED, S.CANCELLED)
    if isinstance(decision, Finish) and decision.state is S.CONFIRMED:
        assert s.sends > 0


# -- route, rounds ------------------------------------------------------------------------


def test_route() -> None:
    assert route(Path.OWN, "V/can0") == Send()
    assert route(Path.ELSEWHERE, "V/can0") == Release()
    assert route(Path.NONE, "V/can0") == End(Undeliverable("no transmit path on bus 'V/can0'"))
    assert unencodable("bad value") == End(Undeliverable("cannot encode: bad value"))


def test_the_hand_over_mark_keeps_the_first_one() -> None:
    assert hand_over_mark(None, T0) == {"state": S.SENDING, "handed_at": T0}
    assert hand_over_mark(T0 - 5, T0) == {"state": S.SENDING, "handed_at": T0 - 5}


def test_a_frame_goes_only_while_pending_and_before_the_expiry() -> None:
    assert may_hand(T0, T0 + 1, pending=True)
    assert not may_hand(T0 + 1, T0 + 1, pending=True)
    assert not may_hand(T0, T0 + 1, pending=False)


@pytest.mark.parametrize(
    ("frames", "handed", "before", "outcome"),
    [
        (1, 1, False, RoundOutcome.COMPLETE),
        (2, 2, True, RoundOutcome.COMPLETE),
        (0, 0, False, RoundOutcome.COMPLETE),
        (2, 1, False, RoundOutcome.PARTIAL),
        (2, 1, True, RoundOutcome.PARTIAL),
        (1, 0, False, RoundOutcome.TAKE_BACK),
        (2, 0, False, RoundOutcome.TAKE_BACK),
        # An earlier round handed frames over: the mark is never taken back.
        (1, 0, True, RoundOutcome.KEEP),
        (2, 0, True, RoundOutcome.KEEP),
    ],
)
def test_after_round(frames: int, handed: int, before: bool, outcome: RoundOutcome) -> None:
    assert after_round(frames, handed, before) is outcome


@given(st.integers(0, 4), st.integers(0, 4), st.booleans())
def test_a_round_that_handed_anything_never_takes_the_mark_back(
    frames: int, handed: int, before: bool
) -> None:
    handed = min(handed, frames)
    outcome = after_round(frames, handed, before)
    if handed or before:
        assert outcome is not RoundOutcome.TAKE_BACK


def test_record_send() -> None:
    assert record_send(0, None, T0) == {
        "sends": 1, "last_sent_at": T0, "updated_at": T0, "state": S.SENDING, "first_sent_at": T0,
    }  # fmt: skip
    assert record_send(2, T0 - 2, T0)["first_sent_at"] == T0 - 2


# -- ending -------------------------------------------------------------------------------

UNSENT = Record(CONTROL, handed_at=None, sends=0, frames_handed=0)
SENT_4 = Record(CONTROL, handed_at=T0, sends=4, frames_handed=0)
# A gateway that recorded the hand-over mark and stopped (killed, its database away) before
# recording anything else: after a restart, its command was maybe sent.
BEGUN_ONLY = Record(CONTROL, handed_at=T0, sends=0, frames_handed=0)
PARTLY = Record(PARAMETERS, handed_at=T0, sends=0, frames_handed=2)
SENT_1_AND_1 = Record(PARAMETERS, handed_at=T0, sends=1, frames_handed=1)
MAYBE = "it may still take effect"
UNRECORDED = (
    f"a send begun at {BEGUN} whose outcome was not recorded (its gateway stopped or its "
    "database failed right after)"
)


@pytest.mark.parametrize(
    ("cause", "record", "end"),
    [
        (Expiry(), UNSENT, Ending(S.EXPIRED, "expired before it could be sent")),
        (Expiry("no transmit path"), UNSENT, Ending(S.EXPIRED, "expired before it could be sent: no transmit path")),
        (Expiry(), SENT_4, Ending(S.UNCONFIRMED, f"sent 4 times, not confirmed by the status flags before expiry; {MAYBE}")),
        (Expiry("link stalled"), SENT_4, Ending(S.UNCONFIRMED, f"sent 4 times, not confirmed by the status flags before expiry; {MAYBE} (last bus error: link stalled)")),
        (Expiry(), replace(SENT_4, kind=REQUEST, sends=1), Ending(S.UNCONFIRMED, f"sent 1 time, no answer from the unit before expiry; {MAYBE}")),
        (Expiry(), PARTLY, Ending(S.UNCONFIRMED, f"2 frames of an unfinished send, expired before all sends (parameter writes have no read-back); {MAYBE}")),
        (Expiry(), SENT_1_AND_1, Ending(S.UNCONFIRMED, f"sent 1 time and 1 frame of an unfinished send, expired before all sends (parameter writes have no read-back); {MAYBE}")),
        (Expiry(), BEGUN_ONLY, Ending(S.UNCONFIRMED, f"{UNRECORDED}, not confirmed by the status flags before expiry; {MAYBE}")),
        (Undeliverable("no transmit path on bus 'V/can0'"), UNSENT, Ending(S.FAILED, "no transmit path on bus 'V/can0'")),
        (Undeliverable("cannot encode: x"), UNSENT, Ending(S.FAILED, "cannot encode: x")),
        (Undeliverable("no transmit path on bus 'V/can0'"), SENT_4, Ending(S.UNCONFIRMED, f"no transmit path on bus 'V/can0'; sent 4 times before, not confirmed: {MAYBE}")),
        (Undeliverable("no transmit path on bus 'V/can0'"), BEGUN_ONLY, Ending(S.UNCONFIRMED, f"no transmit path on bus 'V/can0'; {UNRECORDED} before, not confirmed: {MAYBE}")),
        (Cancel("depot 3"), UNSENT, Ending(S.CANCELLED, "cancelled by depot 3")),
        (Cancel(None), UNSENT, Ending(S.CANCELLED, "cancelled by None")),
        (Cancel("depot 3"), replace(SENT_4, sends=2), Ending(S.CANCELLED, "cancelled by depot 3 after it was sent 2 times: what was sent may still take effect")),
        (Cancel("depot 3"), BEGUN_ONLY, Ending(S.CANCELLED, f"cancelled by depot 3 after it was {UNRECORDED}: what was sent may still take effect")),
        (Abandoned("V/can0"), UNSENT, Ending(S.EXPIRED, "expired before it could be sent: no gateway delivered on V/can0")),
        (Abandoned("V/can0"), SENT_4, Ending(S.UNCONFIRMED, f"sent 4 times, then no gateway delivered on V/can0 before expiry; {MAYBE}")),
        (Abandoned("V/can0"), BEGUN_ONLY, Ending(S.UNCONFIRMED, f"{UNRECORDED}, then no gateway delivered on V/can0 before expiry; {MAYBE}")),
    ],
)  # fmt: skip
def test_ending(cause: EndCause, record: Record, end: Ending) -> None:
    assert ending(cause, record) == end


causes = st.one_of(
    st.builds(Expiry, st.none() | st.text(max_size=20)),
    st.builds(Undeliverable, st.text(max_size=20)),
    st.builds(Cancel, st.none() | st.text(max_size=20)),
    st.builds(Abandoned, st.text(max_size=20)),
)
records = st.builds(
    Record,
    kind=st.sampled_from(CommandKind),
    handed_at=st.none() | st.floats(0, 4e9),
    sends=st.integers(0, 1000),
    frames_handed=st.integers(0, 10),
)


@given(causes, records)
def test_a_command_handed_over_is_never_reported_unsent(cause: EndCause, record: Record) -> None:
    """Once the row records a hand-over (a restart after it included), no cause ends the
    command `expired` or `failed`, and every reason says it may still take effect."""
    end = ending(cause, record)
    assert end.state in (S.EXPIRED, S.FAILED, S.UNCONFIRMED, S.CANCELLED)
    if record.handed_at is not None:
        assert end.state in (S.UNCONFIRMED, S.CANCELLED)
        assert end.reason.endswith("may still take effect") or "may still take effect (" in (
            end.reason
        )
    elif isinstance(cause, Cancel):
        assert end.state is S.CANCELLED
    else:
        assert end.state in (S.EXPIRED, S.FAILED)
        assert "may still take effect" not in end.reason or "may still take effect" in str(cause)


# -- confirmation and refusal -------------------------------------------------------------

ON = {"state_can_jso": "active"}
ACK = {"control": "nack", "acknowledged_pgn": PGN_CONTROL, "address": 0xD8}


@pytest.mark.parametrize(
    ("kind", "first_sent_at", "answers", "baselines", "result"),
    [
        (CONTROL, T0, [(30, (T0 + 1, ON))], {}, True),
        (CONTROL, T0, [(30, (T0 + 1, ON))], {30: T0 - 1}, True),
        (CONTROL, None, [(30, (T0 + 1, ON))], {}, False),  # never sent
        (CONTROL, T0, None, {}, False),  # nothing to confirm it with
        (CONTROL, T0, [(30, None)], {}, False),  # never heard
        (CONTROL, T0, [(30, (T0 - 1, ON))], {30: T0 - 1}, False),  # not since the first send
        (CONTROL, T0, [(30, (T0 + 1, {"state_can_jso": "inactive"}))], {}, False),
        # Every unit reached must show it: one that ignores the frame keeps it unconfirmed.
        (CONTROL, T0, [(30, (T0 + 1, ON)), (31, (T0 + 1, {"state_can_jso": "inactive"}))], {}, False),
        (CONTROL, T0, [(30, (T0 + 1, ON)), (31, (T0 + 2, ON))], {30: T0, 31: T0}, True),
        (REQUEST, T0, [(30, (T0 + 1, {"text": "EQ8001"}))], {30: T0}, True),  # any answer
        (REQUEST, T0, [(30, (T0, {"text": "EQ8001"}))], {30: T0}, False),
    ],
)  # fmt: skip
def test_confirmed(
    kind: CommandKind,
    first_sent_at: float | None,
    answers: list[tuple[int, tuple[float, dict[str, object]] | None]] | None,
    baselines: dict[int, float | None],
    result: bool,
) -> None:
    assert confirmed(kind, first_sent_at, ON, answers, baselines) is result


@pytest.mark.parametrize(
    ("handed_at", "answers", "baselines", "pgn", "result"),
    [
        (T0, [(30, (T0 + 1, ACK))], {}, PGN_CONTROL, "refused by unit 30: NACK for PGN 65490 (0xFFD2)"),
        (None, [(30, (T0 + 1, ACK))], {}, PGN_CONTROL, None),  # nothing handed over yet
        (T0, [(30, (T0 - 1, ACK))], {30: T0 - 1}, PGN_CONTROL, None),  # an older answer
        (T0, [(30, (T0 + 1, ACK))], {}, PGN_PARAMETERS, None),  # about another PGN
        (T0, [(30, (T0 + 1, {**ACK, "address": 0x10}))], {}, PGN_CONTROL, None),  # to another node
        (T0, [(30, (T0 + 1, {**ACK, "control": "cannot_respond"}))], {}, PGN_CONTROL, None),  # busy
        (T0, [(30, (T0 + 1, {**ACK, "control": "ack"}))], {}, PGN_CONTROL, None),
        (T0, [(30, None), (31, (T0 + 1, {**ACK, "control": "access_denied"}))], {}, PGN_CONTROL, "refused by unit 31: access denied for PGN 65490 (0xFFD2)"),
    ],
)  # fmt: skip
def test_refusal(
    handed_at: float | None,
    answers: list[tuple[int, tuple[float, dict[str, object]] | None]],
    baselines: dict[int, float | None],
    pgn: int,
    result: str | None,
) -> None:
    assert refusal(handed_at, answers, baselines, pgn, 0xD8) == result
