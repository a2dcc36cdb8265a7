"""J1939-21 Acknowledgement (PGN 59392, 0xE800): decode and encode, pure.

A node answers a request or a command it will not (or cannot) act on with a NACK, "access
denied" or "cannot respond"; a positive ACK says it acted. Layout (J1939-21): byte 1 the control
byte, byte 2 the group function value, bytes 3-4 reserved (0xFF), byte 5 the address
acknowledged (the requester; 0xFF in units following J1939-21 before 2006), bytes 6-8 the PGN
acknowledged, least significant byte first. Sent to all (DA 0xFF), or to the requester.
"""

from __future__ import annotations

from eqgw.jsontypes import JSONObject
from eqgw.protocol.errors import DecodeError
from eqgw.protocol.j1939 import (
    GLOBAL_ADDRESS,
    PGN_ACKNOWLEDGEMENT,
    PRIORITY_DEFAULT,
    compose_id,
)

CONTROLS = {0: "ack", 1: "nack", 2: "access_denied", 3: "cannot_respond"}
CONTROL_CODES = {name: code for code, name in CONTROLS.items()}
# Answers that end a command as refused ("cannot respond" means busy: try again).
REFUSALS = frozenset({"nack", "access_denied"})


def decode_acknowledgement(data: bytes, da: int) -> JSONObject:
    """The fields of an Acknowledgement frame sent to `da`."""
    if len(data) < 8:
        raise DecodeError(f"acknowledgement of {len(data)} bytes, 8 expected")
    control = CONTROLS.get(data[0])
    if control is None:
        raise DecodeError(f"acknowledgement control byte {data[0]} is not defined")
    return {
        "control": control,
        "group_function": None if data[1] == 0xFF else data[1],
        "address": data[4],
        "acknowledged_pgn": data[5] | (data[6] << 8) | (data[7] << 16),
        "da": da,
    }


def encode_acknowledgement(
    control: str,
    pgn: int,
    *,
    sa: int,
    address: int,
    group_function: int | None = None,
    da: int = GLOBAL_ADDRESS,
) -> tuple[int, bytes]:
    """An Acknowledgement frame from `sa`, about `pgn`, for the node at `address`."""
    data = bytes(
        (
            CONTROL_CODES[control],
            0xFF if group_function is None else group_function,
            0xFF,
            0xFF,
            address,
            pgn & 0xFF,
            (pgn >> 8) & 0xFF,
            (pgn >> 16) & 0xFF,
        )
    )
    return compose_id(PGN_ACKNOWLEDGEMENT, sa, da, PRIORITY_DEFAULT), data


def concerns(fields: JSONObject, pgn: int, requester: int) -> bool:
    """Whether a decoded acknowledgement answers `requester`'s frame of `pgn`: it names that
    PGN, and names the requester (or, older units, nobody) or was sent to it."""
    if fields.get("acknowledged_pgn") != pgn:
        return False
    return fields.get("address") in (requester, GLOBAL_ADDRESS) or fields.get("da") == requester


def describe_answer(fields: JSONObject) -> str:
    """The unit's answer in words: `NACK for PGN 65490 (0xFFD2)`."""
    words = {
        "ack": "ACK",
        "nack": "NACK",
        "access_denied": "access denied",
        "cannot_respond": "cannot respond",
    }
    pgn = fields.get("acknowledged_pgn", 0)
    control = str(fields.get("control", ""))
    text = f"{words.get(control, control)} for PGN {pgn} (0x{pgn:04X})"
    if fields.get("group_function") is not None:
        text += f", group function {fields['group_function']}"
    return text
