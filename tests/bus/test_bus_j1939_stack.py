"""The gateway's bus next to an independent J1939 stack (can-j1939) on one python-can virtual
bus: the stack's ControllerApplication claims, contends, requests and transfers as a vehicle
ECU would, and the gateway's BusReader/BusWriter (configured as `eqgw serve` configures them)
must agree with it frame for frame."""

from __future__ import annotations

import asyncio
import time
from collections.abc import Iterator
from typing import Any

import can
import j1939
import pytest

from eqgw.bus.config import BusConfig
from eqgw.bus.errors import BusNotOpenError
from eqgw.bus.reader import BusReader
from eqgw.bus.writer import BusWriter
from eqgw.config import load_settings
from eqgw.protocol.address_claim import claim_frame
from tests.bus_helpers import TIMEOUT, wait_for

GW = 0xD8
PGN_ADDRESS_CLAIMED = 60928


def gateway_config(channel: str, **claim: Any) -> BusConfig:
    """The bus as `eqgw serve` configures it from a fleet file with no claim settings."""
    settings = load_settings(
        vehicles=[{"id": "BUS-101"}],
        buses=[
            {
                "name": "BUS-101/can0",
                "vehicle_id": "BUS-101",
                "interface": "virtual",
                "channel": channel,
                "bitrate": None,
            }
        ],
        **({"address_claim": claim} if claim else {}),
    )
    return settings.buses[0]


class Observer:
    """Every frame on the bus, with the time it was seen (a plain python-can endpoint)."""

    def __init__(self, channel: str) -> None:
        self.bus = can.Bus(interface="virtual", channel=channel)
        self.seen: list[can.Message] = []

    def drain(self) -> list[can.Message]:
        while (msg := self.bus.recv(0)) is not None:
            self.seen.append(msg)
        return self.seen

    def frames(self, *, sa: int | None = None, pf: int | None = None) -> list[can.Message]:
        return [
            m
            for m in self.drain()
            if (sa is None or m.arbitration_id & 0xFF == sa)
            and (pf is None or (m.arbitration_id >> 16) & 0xFF == pf)
        ]


@pytest.fixture
def observer(channel: str) -> Iterator[Observer]:
    obs = Observer(channel)
    yield obs
    obs.bus.shutdown()


@pytest.fixture
def ecu(channel: str) -> Iterator[j1939.ElectronicControlUnit]:
    """An independent J1939 stack's ECU on the same virtual channel."""
    unit = j1939.ElectronicControlUnit()
    unit.connect(interface="virtual", channel=channel)
    yield unit
    unit.disconnect()
    unit.stop()


def stack_name(industry_group: int, function: int, identity: int) -> j1939.Name:
    return j1939.Name(
        arbitrary_address_capable=0,
        industry_group=industry_group,
        vehicle_system_instance=0,
        vehicle_system=0,
        function=function,
        function_instance=0,
        ecu_instance=0,
        manufacturer_code=0,
        identity_number=identity,
    )


def start_ca(
    ecu: j1939.ElectronicControlUnit, name: j1939.Name, address: int
) -> j1939.ControllerApplication:
    ca = j1939.ControllerApplication(name, address)
    ecu.add_ca(controller_application=ca)
    ca.start()
    return ca


async def test_claims_by_default_before_its_first_frame(channel: str, observer: Observer) -> None:
    config = gateway_config(channel)
    assert config.address_claim_name is not None
    async with BusReader(config) as reader:
        await reader.wait_open(TIMEOUT)
        writer = BusWriter(reader)
        started = time.monotonic()
        await writer.send(0x18EA1ED8, b"\xca\xfe\x00")  # waits for the claim, does not fail
        assert time.monotonic() - started < 5.0
        await wait_for(lambda: len(observer.frames(sa=GW)) >= 2, "the claim and the request")
        claim, request = observer.frames(sa=GW)[:2]
        assert (claim.arbitration_id, bytes(claim.data)) == claim_frame(
            config.address_claim_name, GW
        )
        assert request.arbitration_id == 0x18EA1ED8
        assert request.timestamp - claim.timestamp >= 0.25 - 0.01


async def test_a_weaker_stack_node_backs_off_and_the_gateway_keeps_its_address(
    channel: str, observer: Observer, ecu: j1939.ElectronicControlUnit
) -> None:
    async with BusReader(gateway_config(channel)) as reader:
        await reader.wait_open(TIMEOUT)
        writer = BusWriter(reader)
        await wait_for(writer.may_transmit, "the gateway's claim")
        # Agriculture (industry group 2): a higher NAME than the gateway's on-highway one.
        ca = start_ca(ecu, stack_name(2, 0, 5), GW)
        await wait_for(
            lambda: ca.state == j1939.ControllerApplication.State.CANNOT_CLAIM,
            "the stack's node to give the address up",
        )
        assert writer.may_transmit()
        await writer.send(0x18EA1ED8, b"\xca\xfe\x00")
        assert reader.status().address_claim == "address 216 (0xD8) claimed"


async def test_a_stronger_stack_node_takes_the_address_and_the_gateway_goes_silent(
    channel: str, observer: Observer, ecu: j1939.ElectronicControlUnit
) -> None:
    async with BusReader(gateway_config(channel)) as reader:
        await reader.wait_open(TIMEOUT)
        writer = BusWriter(reader)
        await wait_for(writer.may_transmit, "the gateway's claim")
        ca = start_ca(ecu, stack_name(0, 0, 5), GW)  # global industry group, engine: lower
        await wait_for(lambda: not writer.may_transmit(), "the gateway to lose its claim")
        await wait_for(lambda: bool(observer.frames(sa=0xFE)), "the gateway's 'cannot claim'")
        await wait_for(
            lambda: ca.state == j1939.ControllerApplication.State.NORMAL, "the stack's address"
        )
        assert ca.device_address == GW
        with pytest.raises(BusNotOpenError, match="lost to NAME"):
            await writer.send(0x18EA1ED8, b"\xca\xfe\x00")
        # A request for claims to all: the gateway answers from the null address only.
        observer.drain()
        observer.seen.clear()
        ca.send_request(0, PGN_ADDRESS_CLAIMED, 0xFF)
        await wait_for(lambda: bool(observer.frames(sa=0xFE)), "'cannot claim' to the request")
        await asyncio.sleep(0.3)
        # From 0xD8 only the stack's own request: no claim of the gateway's.
        assert [m.arbitration_id for m in observer.frames(sa=GW)] == [0x18EAFFD8]


async def test_a_stack_request_for_the_gateways_claim_is_answered(
    channel: str, observer: Observer, ecu: j1939.ElectronicControlUnit
) -> None:
    config = gateway_config(channel)
    async with BusReader(config) as reader:
        await reader.wait_open(TIMEOUT)
        await wait_for(BusWriter(reader).may_transmit, "the gateway's claim")
        ca = start_ca(ecu, stack_name(1, 0, 9), 0x80)
        await wait_for(
            lambda: ca.state == j1939.ControllerApplication.State.NORMAL, "the stack's claim"
        )
        observer.drain()
        observer.seen.clear()
        ca.send_request(0, PGN_ADDRESS_CLAIMED, GW)
        await wait_for(lambda: bool(observer.frames(sa=GW, pf=0xEE)), "the gateway's answer")
        answer = observer.frames(sa=GW, pf=0xEE)[0]
        assert config.address_claim_name is not None
        assert (answer.arbitration_id, bytes(answer.data)) == claim_frame(
            config.address_claim_name, GW
        )


async def test_an_opted_out_bus_transmits_without_claiming(
    channel: str, observer: Observer
) -> None:
    config = gateway_config(channel, enabled=False)
    assert config.address_claim_name is None
    async with BusReader(config) as reader:
        await reader.wait_open(TIMEOUT)
        await BusWriter(reader).send(0x18EA1ED8, b"\xca\xfe\x00")
        await wait_for(lambda: bool(observer.frames(sa=GW)), "the request")
        assert observer.frames(sa=GW)[0].arbitration_id == 0x18EA1ED8
