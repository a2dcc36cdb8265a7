"""J1939-81 address claim (PGN 60928) for the gateway's own source address: pure state, no I/O.

A bus's transmit path (eqgw.bus.reader) asks `AddressClaimer.may_transmit` before every frame,
sends `start()`'s frame when the bus opens, and feeds every address claim and request it
receives to `on_frame`, sending what that returns ("cannot claim" frames after
`cannot_claim_delay()`). The gateway is not arbitrary-address capable: a claim it loses ends its
transmissions on that bus (it sends "cannot claim" and stays silent) until the bus is reopened.
`gateway_name` composes the NAME the gateway claims with by default.
"""

from __future__ import annotations

import random
import zlib
from dataclasses import dataclass
from typing import Literal

from eqgw.protocol.j1939 import GLOBAL_ADDRESS, PGN_REQUEST, PRIORITY_DEFAULT, compose_id

PGN_ADDRESS_CLAIMED = 0xEE00  # 60928, PDU1 (sent to the global address)
NULL_ADDRESS = 0xFE  # "cannot claim": the source address of a node without one
# J1939-81: a node claiming an address in 128..247 waits 250 ms for a contending claim before
# it sends anything else; 0..127 and 248..253 may transmit at once.
CLAIM_WAIT_S = 0.25
_REQUEST_FOR_CLAIM = PGN_ADDRESS_CLAIMED.to_bytes(3, "little")
MAX_NAME = (1 << 64) - 1
# J1939-81: a node that cannot claim an address sends "cannot claim" after a pseudo-random
# delay of 0..153 ms (0.6 ms times 0..255), so that several such nodes do not collide.
CANNOT_CLAIM_MAX_DELAY_S = 0.153

# The gateway's default NAME fields (docs/protocol.md#j1939-address-claim): industry group 1
# (on-highway equipment: the equalizers are on trucks, buses and coaches), function 255 (no
# listed function fits a gateway; with the highest function the gateway's NAME loses every
# contention with a vehicle ECU of its industry group), no manufacturer code of its own (0),
# and not arbitrary-address capable.
DEFAULT_INDUSTRY_GROUP = 1
DEFAULT_FUNCTION = 255

Frame = tuple[int, bytes]
ClaimState = Literal["idle", "claiming", "claimed", "lost"]


@dataclass(frozen=True, slots=True)
class J1939Name:
    """The 64-bit J1939 NAME, field by field (J1939-81, least significant field first)."""

    identity_number: int = 0  # 21 bits
    manufacturer_code: int = 0  # 11 bits
    ecu_instance: int = 0  # 3 bits
    function_instance: int = 0  # 5 bits
    function: int = 0  # 8 bits
    vehicle_system: int = 0  # 7 bits (1 reserved bit follows)
    vehicle_system_instance: int = 0  # 4 bits
    industry_group: int = 0  # 3 bits
    arbitrary_address_capable: bool = False

    _WIDTHS = (21, 11, 3, 5, 8, 1, 7, 4, 3, 1)

    def to_int(self) -> int:
        """The NAME as the integer whose little-endian bytes are the claim's payload."""
        values = (
            self.identity_number,
            self.manufacturer_code,
            self.ecu_instance,
            self.function_instance,
            self.function,
            0,  # reserved
            self.vehicle_system,
            self.vehicle_system_instance,
            self.industry_group,
            int(self.arbitrary_address_capable),
        )
        out, shift = 0, 0
        for value, width in zip(values, self._WIDTHS, strict=True):
            if not 0 <= value < (1 << width):
                raise ValueError(f"NAME field value {value} does not fit {width} bits")
            out |= value << shift
            shift += width
        return out

    @classmethod
    def from_int(cls, name: int) -> J1939Name:
        """Split a 64-bit NAME into its fields."""
        if not 0 <= name <= MAX_NAME:
            raise ValueError("a J1939 NAME is a 64-bit unsigned integer")
        fields: list[int] = []
        for width in cls._WIDTHS:
            fields.append(name & ((1 << width) - 1))
            name >>= width
        ident, mfr, ecu, fn_inst, fn, _, vsys, vsys_inst, group, aac = fields
        return cls(ident, mfr, ecu, fn_inst, fn, vsys, vsys_inst, group, bool(aac))


def identity_number_of(text: str) -> int:
    """A 21-bit identity number derived from a text (a bus's name): stable across restarts."""
    return zlib.crc32(text.encode()) & 0x1FFFFF


def gateway_name(
    identity_number: int,
    *,
    industry_group: int = DEFAULT_INDUSTRY_GROUP,
    vehicle_system: int = 0,
    vehicle_system_instance: int = 0,
    function: int = DEFAULT_FUNCTION,
    function_instance: int = 0,
    ecu_instance: int = 0,
    manufacturer_code: int = 0,
) -> int:
    """The gateway's NAME from its fields; ValueError when a field does not fit."""
    return J1939Name(
        identity_number=identity_number,
        manufacturer_code=manufacturer_code,
        ecu_instance=ecu_instance,
        function_instance=function_instance,
        function=function,
        vehicle_system=vehicle_system,
        vehicle_system_instance=vehicle_system_instance,
        industry_group=industry_group,
        arbitrary_address_capable=False,
    ).to_int()


def claim_frame(name: int, address: int) -> Frame:
    """Address Claimed (PGN 60928) from `address`, to all, carrying `name`."""
    return (
        compose_id(PGN_ADDRESS_CLAIMED, address, GLOBAL_ADDRESS, PRIORITY_DEFAULT),
        name.to_bytes(8, "little"),
    )


class AddressClaimer:
    """One node's claim of one address on one bus: what to send, and whether it may send."""

    def __init__(self, name: int, address: int, *, rng: random.Random | None = None) -> None:
        if not 0 <= name <= MAX_NAME:
            raise ValueError("a J1939 NAME is a 64-bit unsigned integer")
        if not 0 <= address <= 253:
            raise ValueError(f"source address {address} is not 0..253")
        self.name = name
        self.address = address
        self.state: ClaimState = "idle"
        self.claimed_at: float | None = None
        self.lost_to: int | None = None  # the NAME that won the address
        self._rng = rng or random.Random()

    def start(self, now: float) -> list[Frame]:
        """Claim the address (on every bus (re)open); returns the claim frame to send."""
        self.state = "claiming"
        self.claimed_at = now
        self.lost_to = None
        return [claim_frame(self.name, self.address)]

    def claim_sent(self, now: float) -> None:
        """The claim frame left at `now`: the 250 ms wait counts from here (J1939-81), not
        from `start`, in case the frame waited behind others."""
        if self.state == "claiming":
            self.claimed_at = now

    def wait_s(self, now: float) -> float:
        """Seconds until the claim may be used; 0 once it may, inf when lost or not started."""
        if self.state == "claimed":
            return 0.0
        if self.state != "claiming" or self.claimed_at is None:
            return float("inf")
        if self.address < 128 or self.address > 247:
            return 0.0
        return max(0.0, self.claimed_at + CLAIM_WAIT_S - now)

    def may_transmit(self, now: float) -> bool:
        """Whether frames other than the claim itself may be sent now."""
        if self.state == "claiming" and self.wait_s(now) == 0.0:
            self.state = "claimed"
        return self.state == "claimed"

    def on_frame(self, can_id: int, data: bytes, now: float) -> list[Frame]:
        """A frame received on the bus; returns the frames to send in answer (maybe none)."""
        pf = (can_id >> 16) & 0xFF
        sa = can_id & 0xFF
        if pf == PGN_ADDRESS_CLAIMED >> 8:
            if sa != self.address or len(data) < 8 or self.state in ("idle", "lost"):
                return []
            other = int.from_bytes(data[:8], "little")
            if other == self.name:
                return []  # our own claim, echoed
            if self.name < other:
                # The lower NAME has priority: ours. Claim again so the other node backs off.
                return [claim_frame(self.name, self.address)]
            self.state = "lost"
            self.lost_to = other
            return [claim_frame(self.name, NULL_ADDRESS)]  # "cannot claim"
        if pf == PGN_REQUEST >> 8:
            da = (can_id >> 8) & 0xFF
            if data[:3] != _REQUEST_FOR_CLAIM or self.state == "idle":
                return []
            if self.state == "lost":
                # Without an address, answer only a request to all, from the null address.
                return [claim_frame(self.name, NULL_ADDRESS)] if da == GLOBAL_ADDRESS else []
            if da in (GLOBAL_ADDRESS, self.address):
                return [claim_frame(self.name, self.address)]
        return []

    def cannot_claim_delay(self) -> float:
        """Seconds to wait before sending a "cannot claim" (J1939-81: 0..153 ms, random)."""
        return self._rng.randint(0, 255) * CANNOT_CLAIM_MAX_DELAY_S / 255

    @staticmethod
    def is_cannot_claim(frame: Frame) -> bool:
        """Whether a frame `on_frame` returned is a "cannot claim" (from the null address)."""
        return frame[0] & 0xFF == NULL_ADDRESS

    def describe(self) -> str:
        """One line for a bus's status: the address and the state of its claim."""
        text = f"address {self.address} (0x{self.address:02X}) {self.state}"
        if self.state == "lost" and self.lost_to is not None:
            text += f" to NAME 0x{self.lost_to:016X}"
        return text
