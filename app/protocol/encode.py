"""Encoding: records back to CAN frames, the exact reverse of decoding (bus writes, simulator)."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import cast

from eqgw.protocol import dbc
from eqgw.protocol.decode import multiplexed_signals, parameter_signals
from eqgw.protocol.dm1 import encode_dm1
from eqgw.protocol.errors import EncodeError
from eqgw.protocol.j1939 import (
    GLOBAL_ADDRESS,
    PGN_BATTERY_STATES,
    PGN_COMPONENT_ID,
    PGN_CONTROL,
    PGN_DM1,
    PGN_HEARTBEAT,
    PGN_PARAMETERS,
    PGN_REQUEST,
    PGN_SOFTWARE_ID,
    PGN_STATUS,
    PGN_VOLTAGES,
    PRIORITY_DEFAULT,
    compose_id,
)
from eqgw.protocol.transport import encode_bam

Frame = tuple[int, bytes]

_BATTERY_OF_INDEX = {1: "12v", 2: "12v", 3: "24v", 4: "24v"}


def _int(value: object) -> int:
    """`int(value)` of a caller's value: a number or a numeric string (else TypeError)."""
    if isinstance(value, int | float | str | bytes):
        return int(value)
    raise TypeError(f"int() argument must be a string or a number, not {type(value).__name__}")


def _raw_value(message_name: str, signal: str, value: object) -> int:
    """Physical value (or choice name, or None) to the raw integer the DBC signal carries."""
    rule = dbc.signal_rules(message_name)[signal]
    if value is None:
        return rule.raw_null()
    if rule.choices is not None:
        if isinstance(value, str):
            for raw, label in rule.choices.items():
                if label == value:
                    return raw
            raise EncodeError(f"{message_name}.{signal}: unknown value {value!r}")
        if isinstance(value, bool):
            return int(value)
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise EncodeError(f"{message_name}.{signal}: {value!r} is not a number")
    raw = rule.to_raw(value)
    limit = 0xFAFF if rule.length == 16 else 0xFA if rule.length == 8 else (1 << rule.length) - 1
    if not 0 <= raw <= limit:
        raise EncodeError(f"{message_name}.{signal}: {value!r} is outside the raw range")
    return raw


def _pack(message_name: str, raw: Mapping[str, int]) -> bytes:
    """Lay raw values out with cantools on the shipped DBC; bits no signal covers are 1."""
    msg = dbc.message(message_name)
    try:
        data: bytes = msg.encode(dict(raw), scaling=False, padding=True, strict=False)
    except Exception as exc:
        raise EncodeError(f"{message_name}: {exc}") from exc
    return data


def _check_fields(name: str, fields: Mapping[str, object], allowed: set[str]) -> None:
    unknown = set(fields) - allowed
    if unknown:
        raise EncodeError(f"{name}: unknown fields {sorted(unknown)}")


def encode_simple(message_name: str, fields: Mapping[str, object]) -> bytes:
    """Payload of a non-multiplexed DBC message; a missing field is "not available"."""
    rules = dbc.signal_rules(message_name)
    _check_fields(message_name, fields, set(rules))
    return _pack(message_name, {s: _raw_value(message_name, s, fields.get(s)) for s in rules})


def encode_battery_states(fields: Mapping[str, object]) -> bytes:
    """Payload of PGN 65497 for one index; names as in the record (battery implied by index)."""
    index = fields.get("index")
    if not isinstance(index, int) or not 1 <= index <= 5:
        raise EncodeError(f"battery_states: index {index!r} is not 1..5")
    battery = _BATTERY_OF_INDEX.get(index)
    if battery and fields.get("battery", battery) != battery:
        raise EncodeError(f"battery_states: index {index} carries the {battery} battery")
    signals = multiplexed_signals("battery_states", index)
    raw: dict[str, int] = {"index": index}
    allowed = {"index", "battery", "temperature_raw", "temperature_implausible"}
    for signal in signals:
        key = signal[: -len(battery) - 1] if battery else signal
        allowed.add(key)
        value = fields.get(key)
        if key == "temperature_c" and fields.get("temperature_raw") is not None:
            raw[signal] = _int(fields["temperature_raw"])
            continue
        raw[signal] = _raw_value("battery_states", signal, value)
    _check_fields("battery_states", fields, allowed)
    return _pack("battery_states", raw)


def encode_parameters(fields: Mapping[str, object]) -> bytes:
    """Payload of PGN 65491 for one index; a value not given is "not requested" (0xFFFF)."""
    index = fields.get("index")
    if not isinstance(index, int):
        raise EncodeError("parameters: index is required")
    signals = parameter_signals(index)
    if not signals:
        raise EncodeError(f"parameters: index {index} is not defined")
    # `out_of_range` is the decoder's flag of what it read (the values carry what was sent).
    _check_fields("parameters", fields, {"index", "out_of_range", *signals})
    raw = {"index": index}
    raw.update({s: _raw_value("parameters", s, fields.get(s)) for s in signals})
    return _pack("parameters", raw)


def encode_request(requested_pgn: int, byte_order: str = "lsb") -> bytes:
    """Payload of PGN 59904: the requested PGN in 3 bytes, padded to the manuals' 8 bytes."""
    if not 0 <= requested_pgn <= 0x3FFFF:
        raise EncodeError(f"request: PGN {requested_pgn} out of range")
    if byte_order == "msb":
        head = bytes(
            [(requested_pgn >> 16) & 0xFF, (requested_pgn >> 8) & 0xFF, requested_pgn & 0xFF]
        )
        return head + b"\xff" * 5
    return _pack("request", {"requested_pgn": requested_pgn})


def _text_payload(prefix: bytes, text: str, suffix: bytes) -> bytes:
    try:
        body = text.encode("ascii")
    except UnicodeEncodeError as exc:
        raise EncodeError(f"identification text {text!r} is not ASCII") from exc
    payload = prefix + body + suffix
    if len(payload) < 8:
        payload += b"\xff" * (8 - len(payload))
    return payload


def _frames(pgn: int, payload: bytes, sa: int, da: int, priority: int) -> list[Frame]:
    if len(payload) <= 8:
        return [(compose_id(pgn, sa, da, priority), payload)]
    return encode_bam(pgn, payload, sa=sa, priority=priority)


def encode(
    name: str,
    fields: Mapping[str, object],
    *,
    sa: int,
    da: int = GLOBAL_ADDRESS,
    priority: int = PRIORITY_DEFAULT,
    series: int = 80,
    request_byte_order: str = "lsb",
) -> list[Frame]:
    """Frames `(can_id, data)` for one record; DM1 and long IDs become a BAM sequence."""
    if name == "status":
        return [(compose_id(PGN_STATUS, sa, priority=priority), encode_simple("status", fields))]
    if name == "heartbeat":
        payload = encode_simple("heartbeat", fields)
        return [(compose_id(PGN_HEARTBEAT, sa, priority=priority), payload)]
    if name == "voltages":
        if series == 70:
            # 70-series: bytes 5-8 unused.
            fields = {k: v for k, v in fields.items() if k not in ("i12", "i24")}
        return [
            (compose_id(PGN_VOLTAGES, sa, priority=priority), encode_simple("voltages", fields))
        ]
    if name == "battery_states":
        payload = encode_battery_states(fields)
        return [(compose_id(PGN_BATTERY_STATES, sa, priority=priority), payload)]
    if name == "dm1":
        _check_fields("dm1", fields, {"lamps", "dtcs"})
        lamps = cast(Mapping[str, object], fields.get("lamps") or {})
        dtcs = cast(Sequence[Mapping[str, object]], fields.get("dtcs") or [])
        payload = encode_dm1(lamps, dtcs)
        return _frames(PGN_DM1, payload, sa, GLOBAL_ADDRESS, priority)
    if name == "component_id":
        payload = _text_payload(b"*", str(fields.get("text", "")), b"*")
        return _frames(PGN_COMPONENT_ID, payload, sa, GLOBAL_ADDRESS, priority)
    if name == "software_id":
        count = _int(fields.get("field_count") or 1)
        if not 0 <= count <= 9:
            raise EncodeError("software_id: field_count is 0..9")
        payload = _text_payload(bytes([0x30 + count]), str(fields.get("text", "")), b"*")
        return _frames(PGN_SOFTWARE_ID, payload, sa, GLOBAL_ADDRESS, priority)
    if name == "control":
        if series != 70 and fields.get("can_ss_msg_en") not in (None, "no_action"):
            # A 70-series command: never send it to an 80-series unit.
            raise EncodeError("control: can_ss_msg_en exists only on the 70-series")
        payload = encode_simple("control", fields)
        return [(compose_id(PGN_CONTROL, sa, priority=priority), payload)]
    if name == "parameters":
        payload = encode_parameters(fields)
        return [(compose_id(PGN_PARAMETERS, sa, priority=priority), payload)]
    if name == "request":
        requested = fields.get("requested_pgn")
        if not isinstance(requested, int):
            raise EncodeError("request: requested_pgn is required")
        target = _int(fields.get("da", da))
        payload = encode_request(requested, request_byte_order)
        return [(compose_id(PGN_REQUEST, sa, target, priority), payload)]
    raise EncodeError(f"unknown message name {name!r}")
