"""The gateway's J1939 address claim on a real (virtual) python-can bus: claimed on
open, answered to requests, defended against a weaker claim, and a lost claim stops every
transmission."""

from __future__ import annotations

import asyncio

import can
import pytest

from eqgw.bus.errors import BusNotOpenError
from eqgw.bus.reader import BusReader
from eqgw.bus.writer import BusWriter
from eqgw.config import load_settings
from eqgw.protocol.address_claim import (
    J1939Name,
    claim_frame,
    gateway_name,
    identity_number_of,
)
from tests.bus.test_bus_reader import virtual_config
from tests.bus_helpers import TIMEOUT, recv_virtual, wait_for

NAME = 0x10FF_0000_0001_B3FC  # industry group 1, function 255, identity 0x1B3FC
CLAIM = claim_frame(NAME, 0xD8)


def _msg(frame: tuple[int, bytes]) -> can.Message:
    return can.Message(arbitration_id=frame[0], data=frame[1], is_extended_id=True)


async def test_off_by_default_nothing_but_the_frames_sent(channel: str, sim: can.BusABC) -> None:
    async with BusReader(virtual_config(channel)) as reader:
        await reader.wait_open(TIMEOUT)
        assert reader.status().address_claim is None and reader.may_transmit()
        await BusWriter(reader).send(0x18EA1ED8, b"\xca\xfe\x00")
        first = await recv_virtual(sim)
        assert first.arbitration_id == 0x18EA1ED8  # no claim before it
        sim.send(_msg((0x18EAFF00, b"\x00\xee\x00")))  # a request for claims: not answered
        await asyncio.sleep(0.3)
        assert sim.recv(0) is None


async def test_claimed_on_open_before_any_frame_and_after_the_250_ms_wait(
    channel: str, sim: can.BusABC
) -> None:
    async with BusReader(virtual_config(channel, address_claim_name=NAME)) as reader:
        await reader.wait_open(TIMEOUT)
        writer = BusWriter(reader)
        await writer.send(0x18EA1ED8, b"\xca\xfe\x00")  # waits for the claim, then goes
        claim = await recv_virtual(sim)
        assert (claim.arbitration_id, bytes(claim.data)) == CLAIM
        request = await recv_virtual(sim)
        assert request.arbitration_id == 0x18EA1ED8
        assert request.timestamp - claim.timestamp >= 0.25 - 0.01
        assert reader.status().address_claim == "address 216 (0xD8) claimed"


async def test_requests_for_the_claim_are_answered(channel: str, sim: can.BusABC) -> None:
    async with BusReader(virtual_config(channel, address_claim_name=NAME)) as reader:
        await reader.wait_open(TIMEOUT)
        assert (await recv_virtual(sim)).arbitration_id == CLAIM[0]
        for request_id in (0x18EAFF00, 0x18EAD800):  # to all, and to the gateway
            sim.send(_msg((request_id, b"\x00\xee\x00")))
            answer = await recv_virtual(sim)
            assert (answer.arbitration_id, bytes(answer.data)) == CLAIM
        sim.send(_msg((0x18EA1E00, b"\x00\xee\x00")))  # to another node: not ours
        await asyncio.sleep(0.3)
        assert sim.recv(0) is None


async def test_a_weaker_contender_is_answered_and_we_keep_transmitting(
    channel: str, sim: can.BusABC
) -> None:
    async with BusReader(virtual_config(channel, address_claim_name=NAME)) as reader:
        await reader.wait_open(TIMEOUT)
        await recv_virtual(sim)
        sim.send(_msg(claim_frame(NAME + 1, 0xD8)))
        answer = await recv_virtual(sim)
        assert (answer.arbitration_id, bytes(answer.data)) == CLAIM
        await BusWriter(reader).send(0x18EA1ED8, b"\xca\xfe\x00")
        assert (await recv_virtual(sim)).arbitration_id == 0x18EA1ED8


async def test_a_lost_claim_stops_transmission_until_the_bus_reopens(
    channel: str, sim: can.BusABC
) -> None:
    reader = BusReader(virtual_config(channel, address_claim_name=NAME), backoff=(0.05, 0.1))
    async with reader:
        await reader.wait_open(TIMEOUT)
        await recv_virtual(sim)
        writer = BusWriter(reader)
        await writer.send(0x18EA1ED8, b"\x01")
        await recv_virtual(sim)
        sim.send(_msg(claim_frame(NAME - 1, 0xD8)))  # a stronger NAME takes 0xD8
        cannot = await recv_virtual(sim)
        assert (cannot.arbitration_id, bytes(cannot.data)) == claim_frame(NAME, 0xFE)
        await wait_for(lambda: not writer.may_transmit(), "the claim to be lost")
        with pytest.raises(BusNotOpenError, match="lost to NAME 0x10FF00000001B3FB"):
            await writer.send(0x18EA1ED8, b"\x02")
        assert "lost" in (reader.status().address_claim or "")
        await asyncio.sleep(0.2)
        assert sim.recv(0) is None  # nothing went out
        # A global request is answered from the null address only.
        sim.send(_msg((0x18EAFF00, b"\x00\xee\x00")))
        answer = await recv_virtual(sim)
        assert answer.arbitration_id == 0x18EEFFFE
        # The bus reopens (adapter replugged): the gateway claims again.
        bus = reader._bus
        assert bus is not None
        reader._connection_failed(reader._generation, "test: reopen")
        await wait_for(lambda: reader.status().reconnects == 1 and reader.may_transmit(), "reopen")
        again = await recv_virtual(sim)
        assert (again.arbitration_id, bytes(again.data)) == CLAIM


def test_claim_is_on_by_default_with_a_documented_name_and_buses_may_opt_out() -> None:
    fleet = {
        "vehicles": [{"id": "A"}],
        "buses": [
            {"name": "a", "vehicle_id": "A", "interface": "virtual", "channel": "x"},
            {
                "name": "b",
                "vehicle_id": "A",
                "interface": "virtual",
                "channel": "y",
                "address_claim_name": "12345",
            },
            {
                "name": "c",
                "vehicle_id": "A",
                "interface": "virtual",
                "channel": "z",
                "address_claim": False,
            },
        ],
    }
    default = load_settings(**fleet)
    names = [b.address_claim_name for b in default.buses]
    assert names[1:] == [12345, None]
    fields = J1939Name.from_int(names[0] or 0)
    assert fields == J1939Name(
        identity_number=identity_number_of("a"),
        industry_group=1,
        function=255,
        arbitrary_address_capable=False,
    )
    ident = load_settings(address_claim={"identity_number": 7, "function_instance": 2}, **fleet)
    assert ident.buses[0].address_claim_name == gateway_name(7, function_instance=2)
    whole = load_settings(address_claim={"name": f"0x{NAME:X}"}, **fleet)
    assert [b.address_claim_name for b in whole.buses] == [NAME, 12345, None]
    off = load_settings(address_claim={"enabled": False}, **fleet)
    assert [b.address_claim_name for b in off.buses] == [None, 12345, None]
    with pytest.raises(Exception, match="64-bit"):
        load_settings(address_claim={"name": 1 << 64}, **fleet)
    with pytest.raises(Exception, match="arbitrary address capable"):
        load_settings(address_claim={"name": "0xA00C810045A1B3FC"}, **fleet)
    with pytest.raises(Exception, match="industry_group"):
        load_settings(address_claim={"industry_group": 8}, **fleet)


async def test_a_closed_bus_says_it_is_closed_not_unclaimed(channel: str) -> None:
    idle = BusWriter(BusReader(virtual_config(channel, address_claim_name=NAME)))
    assert not idle.may_transmit()
    with pytest.raises(BusNotOpenError, match="is closed"):
        await idle.send(0x18EA1ED8, b"\x00")


async def test_a_fenced_bus_sends_nothing_and_claims_again_when_allowed(
    channel: str, sim: can.BusABC
) -> None:
    async with BusReader(virtual_config(channel, address_claim_name=NAME)) as reader:
        await reader.wait_open(TIMEOUT)
        writer = BusWriter(reader)
        assert (await recv_virtual(sim)).arbitration_id == CLAIM[0]
        await wait_for(writer.may_transmit, "the claim")
        reader.set_transmit(False)  # what a fenced cluster node does
        assert not writer.may_transmit()
        with pytest.raises(BusNotOpenError, match="fenced"):
            await writer.send(0x18EA1ED8, b"\xca\xfe\x00")
        sim.send(_msg((0x18EAD800, b"\x00\xee\x00")))  # a request for its claim: no answer
        sim.send(_msg((0x18EAD800, b"\xeb\xfe\x00")))  # for another PGN: no NACK either
        await asyncio.sleep(0.3)
        assert sim.recv(0) is None
        assert reader.status().answers["withheld"] == 1
        reader.set_transmit(True)  # the lease is back: claim first, then transmit
        again = await recv_virtual(sim)
        assert (again.arbitration_id, bytes(again.data)) == CLAIM
        await writer.send(0x18EA1ED8, b"\xca\xfe\x00")
        assert (await recv_virtual(sim)).arbitration_id == 0x18EA1ED8
