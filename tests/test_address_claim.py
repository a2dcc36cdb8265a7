"""J1939 address claim (PGN 60928): the pure state machine, frame by frame."""

from __future__ import annotations

import random

import pytest

from eqgw.protocol.address_claim import (
    CLAIM_WAIT_S,
    NULL_ADDRESS,
    AddressClaimer,
    J1939Name,
    claim_frame,
)

OURS = 0xA00C_8100_45A1_B3FC
LOWER = OURS - 1  # a lower NAME has priority
HIGHER = OURS + 1
GW = 0xD8


def test_name_fields_round_trip_in_j1939_81_layout() -> None:
    name = J1939Name(
        identity_number=0x1B3FC,
        manufacturer_code=0x22D,
        ecu_instance=1,
        function_instance=2,
        function=0x81,
        vehicle_system=6,
        vehicle_system_instance=0,
        industry_group=2,
        arbitrary_address_capable=True,
    )
    value = name.to_int()
    assert value & 0x1FFFFF == 0x1B3FC  # identity number: bits 0-20
    assert (value >> 21) & 0x7FF == 0x22D  # manufacturer code: bits 21-31
    assert (value >> 40) & 0xFF == 0x81  # function: bits 40-47
    assert (value >> 60) & 0x7 == 2  # industry group: bits 60-62
    assert value >> 63 == 1  # arbitrary address capable
    assert J1939Name.from_int(value) == name
    with pytest.raises(ValueError):
        J1939Name(function=256).to_int()


def test_claim_frame_is_pgn_60928_to_all_with_the_name_lsb_first() -> None:
    can_id, data = claim_frame(OURS, GW)
    assert can_id == 0x18EEFFD8
    assert data == bytes.fromhex("FCB3A1450081 0CA0".replace(" ", ""))


def test_an_address_in_128_247_waits_250_ms_after_its_claim() -> None:
    c = AddressClaimer(OURS, GW)
    assert not c.may_transmit(0.0) and c.state == "idle"
    assert c.start(10.0) == [claim_frame(OURS, GW)]
    assert not c.may_transmit(10.0 + CLAIM_WAIT_S - 0.01)
    assert c.wait_s(10.1) == pytest.approx(0.15)
    assert c.may_transmit(10.0 + CLAIM_WAIT_S) and c.state == "claimed"
    low = AddressClaimer(OURS, 0x21)  # 0..127: at once
    low.start(0.0)
    assert low.may_transmit(0.0)


def test_a_contending_higher_name_is_answered_with_our_claim() -> None:
    c = AddressClaimer(OURS, GW)
    c.start(0.0)
    other = claim_frame(HIGHER, GW)
    assert c.on_frame(*other, now=0.1) == [claim_frame(OURS, GW)]
    assert c.may_transmit(1.0) and c.state == "claimed"


def test_a_lower_name_wins_the_address_and_we_stop() -> None:
    c = AddressClaimer(OURS, GW)
    c.start(0.0)
    assert c.may_transmit(1.0)
    answer = c.on_frame(*claim_frame(LOWER, GW), now=2.0)
    assert answer == [(0x18EEFFFE, OURS.to_bytes(8, "little"))]  # cannot claim, from 254
    assert answer[0][0] & 0xFF == NULL_ADDRESS
    assert c.state == "lost" and not c.may_transmit(3.0) and c.wait_s(3.0) == float("inf")
    assert "lost to NAME 0xA00C810045A1B3FB" in c.describe()
    # Further claims change nothing; a new start (the bus reopened) claims again.
    assert c.on_frame(*claim_frame(LOWER, GW), now=4.0) == []
    c.start(5.0)
    assert c.state == "claiming"


def test_claims_for_other_addresses_and_our_own_echo_are_ignored() -> None:
    c = AddressClaimer(OURS, GW)
    c.start(0.0)
    assert c.on_frame(*claim_frame(LOWER, 0x21), now=0.1) == []
    assert c.on_frame(*claim_frame(OURS, GW), now=0.1) == []
    assert c.on_frame(0x18EEFFD8, b"\x00" * 4, now=0.1) == []  # too short to carry a NAME
    assert c.state == "claiming"


@pytest.mark.parametrize(
    ("can_id", "answered"),
    [(0x18EAFF00, True), (0x18EAD800, True), (0x18EA1E00, False)],
)
def test_requests_for_the_address_claim_are_answered(can_id: int, answered: bool) -> None:
    c = AddressClaimer(OURS, GW)
    assert c.on_frame(can_id, b"\x00\xee\x00", now=0.0) == []  # not started: silent
    c.start(0.0)
    want = [claim_frame(OURS, GW)] if answered else []
    assert c.on_frame(can_id, b"\x00\xee\x00", now=0.1) == want
    assert c.on_frame(can_id, b"\xca\xfe\x00", now=0.1) == []  # a request for DM1: not ours


def test_after_losing_only_a_global_request_is_answered_from_the_null_address() -> None:
    c = AddressClaimer(OURS, GW)
    c.start(0.0)
    c.on_frame(*claim_frame(LOWER, GW), now=0.1)
    assert c.on_frame(0x18EAFF00, b"\x00\xee\x00", now=0.2) == [claim_frame(OURS, NULL_ADDRESS)]
    assert c.on_frame(0x18EAD800, b"\x00\xee\x00", now=0.2) == []


def test_bad_arguments() -> None:
    with pytest.raises(ValueError):
        AddressClaimer(1 << 64, GW)
    with pytest.raises(ValueError):
        AddressClaimer(OURS, 254)


def test_the_wait_counts_from_when_the_claim_left() -> None:
    c = AddressClaimer(OURS, GW)
    c.start(0.0)
    c.claim_sent(0.1)  # the frame waited 100 ms behind others
    assert c.wait_s(0.3) == pytest.approx(0.05) and not c.may_transmit(0.3)
    assert c.may_transmit(0.35)
    c.claim_sent(5.0)  # claimed: an answer to a request changes nothing
    assert c.may_transmit(5.0)


def test_cannot_claim_waits_a_random_0_to_153_ms() -> None:
    c = AddressClaimer(OURS, GW, rng=random.Random(7))
    delays = [c.cannot_claim_delay() for _ in range(200)]
    assert all(0.0 <= d <= 0.153 for d in delays)
    assert len(set(delays)) > 50  # spread, not one fixed delay
    assert AddressClaimer.is_cannot_claim(claim_frame(OURS, NULL_ADDRESS))
    assert not AddressClaimer.is_cannot_claim(claim_frame(OURS, GW))
