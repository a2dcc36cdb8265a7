"""The gateway's bus next to an independent J1939 stack (can-j1939) on one python-can virtual
bus: the stack's ControllerApplication claims, contends, requests and transfers as a vehicle
ECU would, and the gateway's BusReader/BusWriter (configured as `eqgw serve` configures them)
must agree with it frame for frame."""

from __future__ import annotations

import asyncio
import time
from collections.abc import Iterator
from typing import Any

import j1939
import pytest

from eqgw.bus.config import BusConfig
from eqgw.bus.errors import BusNotOpenError
from eqgw.bus.reader import BusReader
from eqgw.bus.writer import BusWriter
from eqgw.config import load_settings
from eqgw.protocol.address_claim import claim_frame
from eqgw.protocol.decode import FrameDecoder
from tests.bus_helpers import TIMEOUT, wait_for
from tests.j1939_helpers import Observer, stack_name

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
        # J1939-81: 250 ms from the claim on the wire (not from when it was queued).
        assert request.timestamp - claim.timestamp >= 0.25


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


PGN_ACK = 0xE800
PGN_DM1 = 0xFECA
DM1_3_DTCS = bytes.fromhex("0400a800000100f1e00101f1e101")  # OVF, IMB, EQFLT: 14 bytes


def stack_ca(ecu: j1939.ElectronicControlUnit, address: int) -> j1939.ControllerApplication:
    """A controller application holding `address` without claiming it (the simulated unit's
    address in these tests is taken as given, as the units do)."""
    ca = j1939.ControllerApplication(stack_name(1, 0, address), address, bypass_address_claim=True)
    ecu.add_ca(controller_application=ca)
    return ca


def send_by_rts_cts(
    ecu: j1939.ElectronicControlUnit, pgn: int, sa: int, da: int, data: bytes
) -> None:
    """The stack's own RTS/CTS sender, for a PDU2 PGN too: can-j1939 starts RTS/CTS only for
    PDU1 PGNs (send_pgn broadcasts a PDU2 one by BAM), but J1939-21 sends a PDU2 PGN such as
    DM1 by RTS/CTS in answer to a destination-specific request. This sets up the same sender
    state send_pgn would, with `pgn`; CTS handling, data packets and EoMA are the stack's."""
    dll = ecu.j1939_dll
    packets = -(-len(data) // 7)
    dll._snd_buffer[dll._buffer_hash(sa, da)] = {
        "pgn": pgn,
        "priority": 6,
        "message_size": len(data),
        "num_packages": packets,
        "data": list(data),
        "state": dll.SendBufferState.WAITING_CTS,
        "deadline": time.time() + dll.Timeout.T3,
        "src_address": sa,
        "dest_address": da,
        "next_packet_to_send": 0,
        "next_wait_on_cts": 0,
    }
    dll._J1939_21__send_tp_rts(
        sa, da, 6, pgn, len(data), packets, min(dll._max_cmdt_packets, packets)
    )
    ecu._job_thread_wakeup()


def acks_from_gateway(ecu: j1939.ElectronicControlUnit) -> list[bytes]:
    """Acknowledgements (PGN 59392) from the gateway, as the stack's ECU receives them."""
    got: list[bytes] = []

    def on_message(priority: int, pgn: int, sa: int, timestamp: float, data: bytes) -> None:
        if pgn == PGN_ACK and sa == GW:
            got.append(bytes(data))

    ecu.subscribe(on_message)
    return got


async def test_a_request_to_the_gateway_for_a_pgn_it_does_not_serve_is_nacked(
    channel: str, observer: Observer, ecu: j1939.ElectronicControlUnit
) -> None:
    async with BusReader(gateway_config(channel)) as reader:
        await reader.wait_open(TIMEOUT)
        await wait_for(BusWriter(reader).may_transmit, "the gateway's claim")
        acks = acks_from_gateway(ecu)
        ca = stack_ca(ecu, 0x80)
        ca.send_request(0, 0xFEEB, GW)  # component ID, asked of the gateway
        await wait_for(lambda: bool(acks), "the gateway's NACK")
        # J1939-21: NACK (1), to all, naming the requester (0x80) and the PGN requested.
        assert acks == [bytes([1, 0xFF, 0xFF, 0xFF, 0x80, 0xEB, 0xFE, 0x00])]
        assert observer.frames(sa=GW, pf=0xE8)[0].arbitration_id == 0x18E8FFD8
        # Asked of every node: no NACK (J1939-21), and a request for its claim is answered.
        ca.send_request(0, 0xFEEB, 0xFF)
        ca.send_request(0, PGN_ADDRESS_CLAIMED, GW)
        await wait_for(lambda: bool(observer.frames(sa=GW, pf=0xEE)), "the claim")
        await asyncio.sleep(0.3)
        assert len(acks) == 1


async def test_an_rts_for_a_pgn_the_gateway_does_not_take_is_aborted_at_once(
    channel: str, observer: Observer, ecu: j1939.ElectronicControlUnit
) -> None:
    async with BusReader(gateway_config(channel)) as reader:
        await reader.wait_open(TIMEOUT)
        await wait_for(BusWriter(reader).may_transmit, "the gateway's claim")
        ca = stack_ca(ecu, 0x80)
        ca.send_pgn(0, 0xEF, GW, 6, list(range(20)))  # proprietary A (PDU1), 20 bytes: RTS/CTS
        await wait_for(lambda: bool(observer.frames(sa=GW, pf=0xEC)), "the gateway's answer")
        (abort,) = observer.frames(sa=GW, pf=0xEC)
        assert abort.arbitration_id == 0x1CEC80D8
        assert bytes(abort.data) == bytes([0xFF, 250, 0xFF, 0xFF, 0xFF, 0x00, 0xEF, 0x00])
        # The stack's sender took the abort: its session is over (not waiting out T3).
        await wait_for(lambda: not ecu.j1939_dll._snd_buffer, "the stack to end its session")


async def test_a_dm1_by_rts_cts_to_the_gateway_is_taken_and_decoded(
    channel: str, observer: Observer
) -> None:
    # One packet per CTS, as can-j1939 sends by default: the gateway sends a CTS per packet.
    ecu = j1939.ElectronicControlUnit(max_cmdt_packets=1)
    ecu.connect(interface="virtual", channel=channel)
    try:
        async with BusReader(gateway_config(channel)) as reader:
            await reader.wait_open(TIMEOUT)
            await wait_for(BusWriter(reader).may_transmit, "the gateway's claim")
            stack_ca(ecu, 0x1E)
            send_by_rts_cts(ecu, PGN_DM1, 0x1E, GW, DM1_3_DTCS)
            await wait_for(lambda: not ecu.j1939_dll._snd_buffer, "the stack's transfer to end")
            answers = [bytes(m.data) for m in observer.frames(sa=GW, pf=0xEC)]
            packets = -(-len(DM1_3_DTCS) // 7)
            ctss = [a for a in answers if a[0] == 0x11]
            assert [(a[1], a[2]) for a in ctss] == [(1, seq) for seq in range(1, packets + 1)]
            eoma = bytes([0x13, len(DM1_3_DTCS), 0, packets, 0xFF, 0xCA, 0xFE, 0x00])
            assert answers[-1] == eoma
            assert reader.responder.stats.sessions_completed == 1
            # The gateway's decoder reassembles it from the bus like any transfer.
            dec = FrameDecoder(equalizer_sas=(0x1E,))
            records = [r for m in observer.drain() for r in dec.decode_message(m)]
            (dm1,) = [r for r in records if r.name == "dm1"]
            assert [d["spn"] for d in dm1.fields["dtcs"]] == [168, 520448, 520449]
    finally:
        ecu.disconnect()
        ecu.stop()


async def test_a_dm1_by_rts_cts_between_two_other_nodes_is_counted(
    channel: str, observer: Observer, ecu: j1939.ElectronicControlUnit
) -> None:
    receiver = j1939.ElectronicControlUnit()
    receiver.connect(interface="virtual", channel=channel)
    try:
        stack_ca(receiver, 0x80)
        got: list[int] = []
        receiver.subscribe(lambda prio, pgn, sa, ts, data: got.append(pgn), 0x80)
        stack_ca(ecu, 0x05)
        send_by_rts_cts(ecu, PGN_DM1, 0x05, 0x80, DM1_3_DTCS)
        await wait_for(lambda: PGN_DM1 in got, "the other node to receive the DM1")
        dec = FrameDecoder(equalizer_sas=(0x1E,))
        records = [r for m in observer.drain() for r in dec.decode_message(m)]
        assert records == [] and dec.stats.other_dm1_transfers == 1
    finally:
        receiver.disconnect()
        receiver.stop()
