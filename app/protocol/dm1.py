"""J1939-73 DM1 (active diagnostic trouble codes): decode and encode the payload."""

from __future__ import annotations

from collections.abc import Mapping, Sequence

from eqgw.jsontypes import JSONObject, JSONValue
from eqgw.protocol.errors import DecodeError, EncodeError

# The four DTCs the equalizer reports (both manuals, Table 2; FMI of IMB per SPEC-NOTES errata).
NAMED_CODES: dict[str, tuple[int, int]] = {
    "OVF": (168, 0),
    "UVF": (168, 1),
    "IMB": (520448, 0),
    "EQFLT": (520449, 1),
}
_CODE_BY_SPN_FMI: dict[tuple[int, int], str] = {value: name for name, value in NAMED_CODES.items()}

# Lamp name -> bit shift in byte 1 (J1939-73: PL bits 1-2 ... MIL bits 7-8).
LAMP_SHIFTS: dict[str, int] = {"mil": 6, "rsl": 4, "awl": 2, "pl": 0}
DTC_FIELDS = ("spn", "fmi", "oc", "cm")

ALL_CLEAR = bytes((0x00, 0xFF, 0x00, 0x00, 0x00, 0x00, 0xFF, 0xFF))
SPN_MAX = 0x7FFFF
# A BAM carries at most 1785 bytes: the lamp and reserved bytes plus 4 bytes per DTC.
MAX_DTCS = (1785 - 2) // 4

_DTC_LIMITS: dict[str, int] = {"spn": SPN_MAX, "fmi": 31, "oc": 127, "cm": 1}
_DTC_KEYS = frozenset((*DTC_FIELDS, "code"))
_EMPTY_SLOTS = (b"\x00\x00\x00\x00", b"\xff\xff\xff\xff")


def code_for(spn: int, fmi: int) -> str | None:
    """Name of an equalizer DTC (`OVF`, `UVF`, `IMB`, `EQFLT`), or None for any other SPN/FMI."""
    return _CODE_BY_SPN_FMI.get((spn, fmi))


def decode_dm1(payload: bytes) -> JSONObject:
    """Decode a DM1 payload (single frame or BAM-reassembled) into lamps and DTCs."""
    data = bytes(payload)
    if len(data) < 2:
        raise DecodeError(f"DM1 needs at least 2 bytes, got {len(data)}")
    lamp_byte = data[0]
    lamps: JSONObject = {name: (lamp_byte >> shift) & 0x3 for name, shift in LAMP_SHIFTS.items()}
    dtcs: list[JSONValue] = []
    # Byte 2 is reserved (0xFF or 0x00 in the manuals); a trailing partial slot is padding.
    for start in range(2, len(data) - 3, 4):
        slot = data[start : start + 4]
        if slot in _EMPTY_SLOTS:
            continue
        spn = slot[0] | (slot[1] << 8) | ((slot[2] >> 5) << 16)
        fmi = slot[2] & 0x1F
        dtcs.append(
            {
                "spn": spn,
                "fmi": fmi,
                "oc": slot[3] & 0x7F,
                "cm": slot[3] >> 7,
                "code": code_for(spn, fmi),
            }
        )
    return {"lamps": lamps, "dtcs": dtcs}


def _int_field(what: str, value: object, limit: int) -> int:
    # bool is an int subclass; True as an SPN is a caller bug, not a value.
    if isinstance(value, bool) or not isinstance(value, int):
        raise EncodeError(f"{what} must be an int, got {value!r}")
    if not 0 <= value <= limit:
        raise EncodeError(f"{what} {value} out of range 0..{limit}")
    return value


def _lamp_byte(lamps: Mapping[str, object]) -> int:
    unknown = set(lamps) - set(LAMP_SHIFTS)
    if unknown:
        raise EncodeError(f"unknown lamp(s) {sorted(unknown)}; expected {sorted(LAMP_SHIFTS)}")
    byte = 0
    for name, shift in LAMP_SHIFTS.items():
        value = lamps.get(name)
        if value is not None:
            byte |= _int_field(f"lamp {name}", value, 3) << shift
    return byte


def _dtc_bytes(index: int, dtc: Mapping[str, object]) -> bytes:
    unknown = set(dtc) - _DTC_KEYS
    if unknown:
        raise EncodeError(f"DTC {index}: unknown field(s) {sorted(unknown)}")
    values: dict[str, int] = {}
    for name, limit in _DTC_LIMITS.items():
        value = dtc.get(name)
        if value is None:
            if name in ("spn", "fmi"):
                raise EncodeError(f"DTC {index}: {name} is required")
            value = 0
        values[name] = _int_field(f"DTC {index} {name}", value, limit)
    spn = values["spn"]
    slot = bytes(
        (
            spn & 0xFF,
            (spn >> 8) & 0xFF,
            ((spn >> 16) << 5) | values["fmi"],
            (values["cm"] << 7) | values["oc"],
        )
    )
    if slot in _EMPTY_SLOTS:
        # A receiver reads these as "no DTC", so the DTC would silently vanish.
        raise EncodeError(f"DTC {index} encodes as {slot.hex()}, which means 'no DTC'")
    return slot


def encode_dm1(lamps: Mapping[str, object], dtcs: Sequence[Mapping[str, object]]) -> bytes:
    """Build a DM1 payload: 8 bytes for 0 or 1 DTC, 2 + 4n bytes (a BAM payload) for n > 1."""
    lamp_byte = _lamp_byte(lamps)
    if len(dtcs) > MAX_DTCS:
        raise EncodeError(f"{len(dtcs)} DTCs do not fit a BAM (at most {MAX_DTCS})")
    if not dtcs:
        return bytes((lamp_byte,)) + ALL_CLEAR[1:]
    body = b"".join(_dtc_bytes(i, dtc) for i, dtc in enumerate(dtcs, start=1))
    # The manuals' tables put 0x00 in the reserved byte whenever a DTC is active.
    head = bytes((lamp_byte, 0x00))
    if len(dtcs) == 1:
        return head + body + b"\xff\xff"
    return head + body
