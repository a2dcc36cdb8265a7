"""SAE J1939 identifiers: split and compose priority, PGN, source and destination addresses."""

from __future__ import annotations

from dataclasses import dataclass

GLOBAL_ADDRESS = 0xFF
DEFAULT_EQUALIZER_SA = 0x1E
DEFAULT_GATEWAY_SA = 0xD8

# Equalizer PGNs (both series) and the J1939 PGNs the equalizer uses.
PGN_CONTROL = 0xFFD2  # 65490, to the equalizer
PGN_PARAMETERS = 0xFFD3  # 65491, to the equalizer
PGN_STATUS = 0xFFD4  # 65492
PGN_HEARTBEAT = 0xFFD5  # 65493
PGN_VOLTAGES = 0xFFD6  # 65494
PGN_BATTERY_STATES = 0xFFD9  # 65497, 80-series only
PGN_DM1 = 0xFECA  # 65226 (the manuals misprint 65526)
PGN_COMPONENT_ID = 0xFEEB  # 65259
# The 70-series manual's id for component ID; accepted when the payload starts "*EQ".
PGN_COMPONENT_ID_70_MISPRINT = 0xFEED
PGN_SOFTWARE_ID = 0xFEDA  # 65242
PGN_REQUEST = 0xEA00  # 59904, PDU1
PGN_TP_CM = 0xEC00  # 60416, PDU1
PGN_TP_DT = 0xEB00  # 60160, PDU1
PGN_ACKNOWLEDGEMENT = 0xE800  # 59392, PDU1 (J1939-21 ACK/NACK)

PRIORITY_DEFAULT = 6
PRIORITY_TP_DT = 7


@dataclass(frozen=True, slots=True)
class J1939Id:
    """The parts of a 29-bit J1939 identifier."""

    priority: int
    edp: int
    dp: int
    pf: int
    ps: int
    sa: int

    @property
    def is_pdu1(self) -> bool:
        return self.pf < 240

    @property
    def pgn(self) -> int:
        """Parameter group number; for PDU1 the PS byte is a destination, not part of it."""
        base = (self.edp << 17) | (self.dp << 16) | (self.pf << 8)
        return base if self.pf < 240 else base | self.ps

    @property
    def da(self) -> int:
        """Destination address: PS for PDU1, global for PDU2 broadcasts."""
        return self.ps if self.pf < 240 else GLOBAL_ADDRESS


def parse_id(can_id: int) -> J1939Id:
    """Split a 29-bit identifier into its J1939 fields."""
    return J1939Id(
        priority=(can_id >> 26) & 0x7,
        edp=(can_id >> 25) & 0x1,
        dp=(can_id >> 24) & 0x1,
        pf=(can_id >> 16) & 0xFF,
        ps=(can_id >> 8) & 0xFF,
        sa=can_id & 0xFF,
    )


def pgn_of(can_id: int) -> int:
    """PGN of a 29-bit identifier (fast path used on every frame)."""
    pf = (can_id >> 16) & 0xFF
    if pf < 240:
        return (can_id >> 8) & 0x3FF00
    return (can_id >> 8) & 0x3FFFF


def compose_id(
    pgn: int, sa: int, da: int = GLOBAL_ADDRESS, priority: int = PRIORITY_DEFAULT
) -> int:
    """Build a 29-bit identifier; `da` is used only for PDU1 PGNs."""
    if not 0 <= pgn <= 0x3FFFF:
        raise ValueError(f"PGN {pgn} out of range")
    if not 0 <= sa <= 0xFF or not 0 <= da <= 0xFF:
        raise ValueError("addresses are 0..255")
    if not 0 <= priority <= 7:
        raise ValueError("priority is 0..7")
    pf = (pgn >> 8) & 0xFF
    if pf < 240:
        if pgn & 0xFF:
            raise ValueError(f"PDU1 PGN {pgn:#x} must have a zero low byte")
        pgn = pgn | da
    return (priority << 26) | (pgn << 8) | sa
