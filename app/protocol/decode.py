"""Frame decoding: CAN frames in, equalizer records out, with SPEC-NOTES' null and errata rules."""

from __future__ import annotations

from collections.abc import Callable, Iterable, Iterator, Mapping
from dataclasses import dataclass, field
from typing import Protocol

from eqgw.jsontypes import JSONObject, JSONValue
from eqgw.protocol import dbc
from eqgw.protocol.acknowledgement import decode_acknowledgement
from eqgw.protocol.dm1 import decode_dm1
from eqgw.protocol.errors import DecodeError
from eqgw.protocol.j1939 import (
    DEFAULT_EQUALIZER_SA,
    GLOBAL_ADDRESS,
    PGN_ACKNOWLEDGEMENT,
    PGN_BATTERY_STATES,
    PGN_COMPONENT_ID,
    PGN_COMPONENT_ID_70_MISPRINT,
    PGN_CONTROL,
    PGN_DM1,
    PGN_HEARTBEAT,
    PGN_PARAMETERS,
    PGN_REQUEST,
    PGN_SOFTWARE_ID,
    PGN_STATUS,
    PGN_TP_CM,
    PGN_TP_DT,
    PGN_VOLTAGES,
)
from eqgw.protocol.records import Record
from eqgw.protocol.transport import (
    BamReassembler,
    RtsCtsReassembler,
    Transfer,
    announced_pgn,
    is_rts,
)

# Battery-state indexes 1-4 carry one battery each; the DBC suffixes their signal names.
_BATTERY_OF_INDEX = {1: "12v", 2: "12v", 3: "24v", 4: "24v"}
_PERCENT_FIELDS = frozenset({"soc_achievable", "soh", "dod", "soc"})
TEMPERATURE_PLAUSIBLE_C = (-60.0, 150.0)
# The equalizer's own proprietary PGNs: from another address, another vendor's or an
# equalizer's at an address not configured (`DecodeStats.lookalike`).
LOOKALIKE_PGNS = frozenset({PGN_STATUS, PGN_HEARTBEAT, PGN_VOLTAGES, PGN_BATTERY_STATES})
# Payloads reassembled from a BAM that we decode (anything else from an equalizer is ignored).
_TRANSPORTED = frozenset({PGN_DM1, PGN_COMPONENT_ID, PGN_SOFTWARE_ID})
# What a request must ask for to be an equalizer record when it is sent to all (the manuals:
# "the Request Message supports requests for DM1, Software ID, and Component ID messages";
# 0xFEED is the 70-series manual's misprint of the Component ID PGN, which the units answer).
ANSWERED_PGNS = frozenset(
    {PGN_DM1, PGN_COMPONENT_ID, PGN_COMPONENT_ID_70_MISPRINT, PGN_SOFTWARE_ID}
)
# A classic CAN (J1939) frame carries at most 8 data bytes; a longer one is malformed.
MAX_DATA_BYTES = 8
_CACHE_LIMIT = 4096
_IGNORED_IDS_LIMIT = 65536


class FrameLike(Protocol):
    """The parts of a `can.Message` the decoder reads."""

    @property
    def timestamp(self) -> float: ...
    @property
    def channel(self) -> object: ...
    @property
    def arbitration_id(self) -> int: ...
    @property
    def data(self) -> bytes | bytearray: ...
    @property
    def is_extended_id(self) -> bool: ...
    @property
    def is_remote_frame(self) -> bool: ...
    @property
    def is_error_frame(self) -> bool: ...


@dataclass(slots=True)
class DecodeStats:
    """What happened to every frame: each lands in exactly one of the frame counters."""

    decoded_frames: int = 0
    transport_frames: int = 0
    ignored: int = 0
    malformed: int = 0
    records: int = 0
    transfers_completed: int = 0
    transfers_incomplete: int = 0
    transfers_broken: int = 0
    # DM1s other nodes (not the equalizers) announced to one another by RTS/CTS: not decoded
    # (they are not the equalizers' faults), counted.
    other_dm1_transfers: int = 0
    by_name: dict[str, int] = field(default_factory=dict)
    # Frames of the equalizer's own proprietary PGNs (status, heartbeat, voltages, battery
    # states) from source addresses not decoded, per address: another vendor's device, or an
    # equalizer at an address nobody named (counted among `ignored`).
    lookalike: dict[int, int] = field(default_factory=dict)

    @property
    def frames(self) -> int:
        """Frames read: every frame is counted in exactly one of the four frame counters."""
        return self.decoded_frames + self.transport_frames + self.ignored + self.malformed

    def as_dict(self) -> JSONObject:
        return {
            "frames": self.frames,
            "records": self.records,
            "ignored": self.ignored,
            "malformed": self.malformed,
            "transport_frames": self.transport_frames,
            "transfers_completed": self.transfers_completed,
            "transfers_incomplete": self.transfers_incomplete,
            "transfers_broken": self.transfers_broken,
            "other_dm1_transfers": self.other_dm1_transfers,
            "by_name": dict(sorted(self.by_name.items())),
            "lookalike": {str(sa): n for sa, n in sorted(self.lookalike.items())},
        }


def _copy_fields(fields: JSONObject) -> JSONObject:
    """A copy deep enough that no caller can change another record's (or the cache's) fields."""
    out: JSONObject = {}
    for key, value in fields.items():
        if isinstance(value, dict):
            value = dict(value)
        elif isinstance(value, list):
            value = [dict(v) if isinstance(v, dict) else v for v in value]
        out[key] = value
    return out


def lookalike_summary(lookalike: dict[int, int], decoded: Iterable[int]) -> str:
    """One line naming the addresses that sent the equalizer's own proprietary PGNs without
    being decoded (`DecodeStats.lookalike`), and the `--sa` that would decode them too."""
    named = ", ".join(f"SA {sa} ({n:,} frames)" for sa, n in sorted(lookalike.items()))
    sas = ",".join(str(sa) for sa in sorted({*decoded, *lookalike}))
    return (
        f"equalizer-like frames (PGN 0xFFD4-0xFFD9) from addresses not decoded: {named}; "
        f"other vendors' devices, or equalizers: to decode them, --sa {sas}"
    )


def series_from_text(text: str) -> int | None:
    """70 or 80 from an identification text such as "EQ8001"."""
    if len(text) >= 4 and text[:2] == "EQ" and text[2:4] in ("70", "80"):
        return int(text[2:4])
    return None


def _ascii(payload: bytes) -> str:
    text = payload.decode("ascii", errors="replace")
    return text.strip("*\x00\xff\ufffd ").replace("\ufffd", "?")


def _identification(text: str) -> JSONObject:
    revision: int | None = None
    tail = text[4:6]
    if len(tail) == 2 and tail.isdigit():
        revision = int(tail)
    return {"text": text, "series": series_from_text(text), "revision": revision}


def decode_component_id(payload: bytes) -> JSONObject:
    """Component ID (`*EQ8001*`): text without delimiters, series, revision."""
    if not payload:
        raise DecodeError("empty component ID")
    text = _ascii(payload).split("*")[0]
    return _identification(text)


def decode_software_id(payload: bytes) -> JSONObject:
    """Software ID: byte 1 the number of fields (the unit sends ASCII "1"), then `EQ8001*`."""
    if len(payload) < 2:
        raise DecodeError("software ID shorter than 2 bytes")
    count_byte = payload[0]
    field_count = count_byte - 0x30 if 0x30 <= count_byte <= 0x39 else count_byte
    text = _ascii(payload[1:]).split("*")[0]
    fields = _identification(text)
    fields["field_count"] = field_count
    return fields


def _raw_signals(message_name: str, data: bytes) -> dict[str, int]:
    """Raw signal values that fit in the payload, extracted by cantools from the shipped DBC."""
    try:
        raw: dict[str, int] = dbc.message(message_name).decode(
            data, decode_choices=False, scaling=False, allow_truncated=True
        )  # type: ignore[assignment]
    except Exception as exc:  # cantools raises several types for bad multiplexer values
        raise DecodeError(f"{message_name}: {exc}") from exc
    return raw


def _scaled(message_name: str, raw: Mapping[str, int]) -> JSONObject:
    rules = dbc.signal_rules(message_name)
    return {name: rules[name].to_physical(value) for name, value in raw.items()}


def decode_status(data: bytes) -> JSONObject:
    """PGN 65492: 16 two-bit flags; flags whose byte is missing are null."""
    fields = _scaled("status", _raw_signals("status", data))
    if not fields:
        raise DecodeError("status frame has no data")
    for name in dbc.signal_rules("status"):
        fields.setdefault(name, None)
    return fields


def decode_heartbeat(data: bytes) -> JSONObject:
    """PGN 65493: the alternating two-bit heartbeat."""
    raw = _raw_signals("heartbeat", data)
    if not raw:
        raise DecodeError("heartbeat frame has no data")
    return {"heartbeat": raw["heartbeat"]}


_VOLTAGES: dbc.SignalExtractor | None = None


def decode_voltages(data: bytes, series: int | None = None) -> JSONObject:
    """PGN 65494: V12, V24 and (80-series) I12, I24."""
    global _VOLTAGES
    if len(data) < 2:
        raise DecodeError("voltages frame too short for any field")
    extractor = _VOLTAGES
    if extractor is None:
        extractor = _VOLTAGES = dbc.SignalExtractor("voltages")
    try:
        fields = extractor.physical(extractor.raw(data))
    except Exception as exc:
        raise DecodeError(f"voltages: {exc}") from exc
    if series == 70:
        # 70-series bytes 5-8 are unused: whatever they hold is not a current.
        fields["i12"] = fields["i24"] = None
    return fields


def decode_battery_states(data: bytes) -> JSONObject:
    """PGN 65497: battery states multiplexed by the index byte (1-5)."""
    if not data:
        raise DecodeError("battery states frame has no index")
    index = data[0]
    if not 1 <= index <= 5:
        raise DecodeError(f"battery states index {index} is not defined")
    rules = dbc.signal_rules("battery_states")
    raw = _raw_signals("battery_states", data)
    expected = multiplexed_signals("battery_states", index)
    fields: JSONObject = {"index": index}
    battery = _BATTERY_OF_INDEX.get(index)
    suffix = f"_{battery}" if battery else ""
    if battery:
        fields["battery"] = battery
    for name in expected:
        value = rules[name].to_physical(raw[name]) if name in raw else None
        key = name[: -len(suffix)] if suffix and name.endswith(suffix) else name
        if key in _PERCENT_FIELDS and isinstance(value, float | int) and value > 100.0:
            value = None
        fields[key] = value
    if index == 5:
        raw_t = raw.get("temperature_c")
        fields["temperature_raw"] = raw_t
        t = fields.get("temperature_c")
        lo, hi = TEMPERATURE_PLAUSIBLE_C
        fields["temperature_implausible"] = (
            None if not isinstance(t, float | int) else not lo <= t <= hi
        )
    if len(raw) <= 1:
        raise DecodeError(f"battery states index {index}: no field present")
    return fields


def _build_mux_signals() -> dict[tuple[str, int], list[str]]:
    """Signal names per (message, multiplexer value), in DBC order."""
    table: dict[tuple[str, int], list[str]] = {}
    for msg_name in ("battery_states", "parameters"):
        for sig in dbc.message(msg_name).signals:
            for mux in sig.multiplexer_ids or ():
                table.setdefault((msg_name, mux), []).append(sig.name)
    return table


_MUX_SIGNALS: dict[tuple[str, int], list[str]] = {}


def multiplexed_signals(message_name: str, index: int) -> list[str]:
    """DBC signal names carried by one index of a multiplexed message."""
    if not _MUX_SIGNALS:
        _MUX_SIGNALS.update(_build_mux_signals())
    return _MUX_SIGNALS.get((message_name, index), [])


def parameter_signals(index: int) -> list[str]:
    """Names of the parameter fields carried by one index of PGN 65491."""
    return multiplexed_signals("parameters", index)


def decode_parameters(data: bytes) -> JSONObject:
    """PGN 65491 (to the equalizer): index plus that index's values; 0xFF00.. is not requested."""
    if not data:
        raise DecodeError("parameters frame has no index")
    index = data[0]
    names = parameter_signals(index)
    if not names:
        raise DecodeError(f"parameters index {index} is not defined")
    raw = _raw_signals("parameters", data)
    rules = dbc.signal_rules("parameters")
    fields: JSONObject = {"index": index}
    present = 0
    for name in names:
        if name in raw:
            fields[name] = rules[name].to_physical(raw[name])
            present += 1
        else:
            fields[name] = None
    if not present:
        # Not even the first value's bytes: a frame with no field is not a record.
        raise DecodeError(f"parameters index {index}: no field present")
    # PGN 65491 is proprietary: another vendor's frame, or a bad write, may carry values the
    # manuals do not allow (an OV setpoint of 1,333 V). Flagged, never silently shown as real.
    out_of_range: list[JSONValue] = [
        name for name in names if (v := fields[name]) is not None and not _in_range(rules[name], v)
    ]
    if out_of_range:
        fields["out_of_range"] = out_of_range
    return fields


def _in_range(rule: dbc.SignalRule, value: JSONValue) -> bool:
    lo, hi = rule.minimum, rule.maximum
    if lo is None and hi is None:
        return True
    if not isinstance(value, float | int):
        raise TypeError(f"{rule.name}: {value!r} is not a number")
    return (lo is None or value >= lo) and (hi is None or value <= hi)


def decode_control(data: bytes) -> JSONObject:
    """PGN 65490 (to the equalizer): four two-bit commands."""
    fields = _scaled("control", _raw_signals("control", data))
    if not fields:
        raise DecodeError("control frame has no data")
    return fields


def decode_request(data: bytes, da: int, byte_order: str = "lsb") -> JSONObject:
    """PGN 59904: the requested PGN (J1939-21 order, LSB first, unless configured otherwise)."""
    if len(data) < 3:
        raise DecodeError("request shorter than 3 bytes")
    if byte_order == "msb":
        pgn = (data[0] << 16) | (data[1] << 8) | data[2]
    else:
        pgn = _raw_signals("request", bytes(data[:3]))["requested_pgn"]
    return {"requested_pgn": pgn, "da": da}


class FrameDecoder:
    """Decodes every equalizer message of a stream of frames; keeps counters; never raises."""

    def __init__(
        self,
        equalizer_sas: Iterable[int] = (DEFAULT_EQUALIZER_SA,),
        *,
        request_byte_order: str = "lsb",
        series: Mapping[tuple[str | None, int], int] | None = None,
        bam_timeout: float = 0.75,
        only: Iterable[str] | None = None,
    ) -> None:
        multiplexed_signals("parameters", 0)  # build the table before the hot path
        self.equalizer_sas = frozenset(equalizer_sas)
        self.request_byte_order = request_byte_order
        self._series: dict[tuple[str | None, int], int] = dict(series or {})
        self._bam = BamReassembler(t1=bam_timeout)
        self._rts = RtsCtsReassembler()
        self._only = frozenset(only) if only is not None else None
        self.stats = DecodeStats()
        self._bad_payloads = 0
        self._cache: dict[tuple[int, bytes], JSONObject] = {}
        # 29-bit ids of other nodes' frames that are never equalizer data, whatever the payload.
        self._ignored_ids: set[int] = set()
        self._from_equalizer: dict[int, tuple[str, Callable[[bytes], JSONObject]]] = {
            PGN_STATUS: ("status", decode_status),
            PGN_HEARTBEAT: ("heartbeat", decode_heartbeat),
            PGN_BATTERY_STATES: ("battery_states", decode_battery_states),
            PGN_DM1: ("dm1", decode_dm1),
            PGN_COMPONENT_ID: ("component_id", decode_component_id),
            PGN_SOFTWARE_ID: ("software_id", decode_software_id),
        }
        self._to_equalizer: dict[int, tuple[str, Callable[[bytes], JSONObject]]] = {
            PGN_CONTROL: ("control", decode_control),
            PGN_PARAMETERS: ("parameters", decode_parameters),
        }

    def forget(self, channel: str | None, sa: int) -> None:
        """Forget what was learned of a unit (its series): another node took its address."""
        self._series.pop((channel, sa), None)

    def series_of(self, channel: str | None, sa: int) -> int | None:
        """The series learned (or configured) for a unit, if any."""
        return self._series.get((channel, sa))

    def decode_message(self, msg: FrameLike) -> list[Record]:
        """Decode a `can.Message`."""
        # Fast path: most frames on a vehicle bus come from other nodes; their ids are
        # remembered so the next frame with the same id costs one set lookup.
        can_id = msg.arbitration_id
        if can_id in self._ignored_ids and msg.is_extended_id and len(msg.data) <= MAX_DATA_BYTES:
            self.stats.ignored += 1
            return []
        channel = msg.channel
        return self.decode(
            msg.timestamp,
            channel if channel is None or type(channel) is str else str(channel),
            can_id,
            bytes(msg.data),
            is_extended=msg.is_extended_id,
            is_remote=msg.is_remote_frame,
            is_error=msg.is_error_frame,
        )

    def decode_frames(
        self, frames: Iterable[tuple[float, str | None, int, bytes, bool, bool, bool]]
    ) -> Iterator[Record]:
        """Records of `(ts, channel, can_id, data, extended, remote, error)` tuples, in order
        (the fast path of `eqgw decode`: no `can.Message` per frame)."""
        ignored_ids = self._ignored_ids
        stats = self.stats
        decode = self.decode
        for ts, channel, can_id, data, extended, remote, error in frames:
            if can_id in ignored_ids and extended and len(data) <= MAX_DATA_BYTES:
                stats.ignored += 1
                continue
            records = decode(
                ts, channel, can_id, data, is_extended=extended, is_remote=remote, is_error=error
            )
            if records:
                yield from records

    def decode(
        self,
        ts: float,
        channel: str | None,
        can_id: int,
        data: bytes,
        *,
        is_extended: bool = True,
        is_remote: bool = False,
        is_error: bool = False,
    ) -> list[Record]:
        """Decode one frame; returns zero, one or (a completed BAM) one record."""
        stats = self.stats
        if not is_extended or is_remote or is_error:
            stats.ignored += 1
            return []
        if len(data) > MAX_DATA_BYTES or ts - ts != 0.0:
            # CAN FD or a corrupt log: J1939 frames carry at most 8 bytes; never decoded. A
            # NaN or infinite timestamp (ts - ts is NaN) cannot be stored or ordered.
            stats.malformed += 1
            return []
        sa = can_id & 0xFF
        pf = (can_id >> 16) & 0xFF
        pgn = (can_id >> 8) & (0x3FF00 if pf < 240 else 0x3FFFF)
        try:
            if sa in self.equalizer_sas:
                entry = self._from_equalizer.get(pgn)
                if entry is not None:
                    return self._emit(ts, channel, sa, pgn, entry, data)
                if pgn == PGN_VOLTAGES:
                    fields = decode_voltages(data, self._series.get((channel, sa)))
                    return self._record(ts, channel, sa, pgn, "voltages", fields)
                if pgn in (PGN_TP_CM, PGN_TP_DT):
                    return self._transport(ts, channel, sa, (can_id >> 8) & 0xFF, pgn, data)
                if pgn == PGN_ACKNOWLEDGEMENT:
                    fields = decode_acknowledgement(data, (can_id >> 8) & 0xFF)
                    return self._record(ts, channel, sa, pgn, "acknowledgement", fields)
                if pgn == PGN_COMPONENT_ID_70_MISPRINT and data[:3] == b"*EQ":
                    fields = decode_component_id(data)
                    return self._record(ts, channel, sa, pgn, "component_id", fields)
            elif pgn in LOOKALIKE_PGNS:
                # Not decoded, and not remembered as ignored: every frame is counted by address.
                stats.lookalike[sa] = stats.lookalike.get(sa, 0) + 1
                stats.ignored += 1
                return []
            entry = self._to_equalizer.get(pgn)
            if entry is not None:
                return self._emit(ts, channel, sa, pgn, entry, data)
            if pgn == PGN_TP_CM:
                # Another node's transport session: a DM1 one node sends another by RTS/CTS
                # is counted (the id is not remembered as ignored: the next may be one).
                if is_rts(data) and announced_pgn(data) == PGN_DM1:
                    stats.other_dm1_transfers += 1
                stats.ignored += 1
                return []
            if pgn == PGN_REQUEST:
                da = (can_id >> 8) & 0xFF
                if da in self.equalizer_sas:
                    fields = decode_request(data, da, self.request_byte_order)
                    return self._record(ts, channel, sa, pgn, "request", fields)
                if da == GLOBAL_ADDRESS:
                    # Sent to all: an equalizer record only if it asks for what a unit answers.
                    # The id is not remembered as ignored: the next request may be for DM1.
                    fields = decode_request(data, da, self.request_byte_order)
                    if fields["requested_pgn"] in ANSWERED_PGNS:
                        return self._record(ts, channel, sa, pgn, "request", fields)
                    stats.ignored += 1
                    return []
        except DecodeError:
            stats.malformed += 1
            return []
        if sa not in self.equalizer_sas and len(self._ignored_ids) < _IGNORED_IDS_LIMIT:
            self._ignored_ids.add(can_id)
        stats.ignored += 1
        return []

    def _emit(
        self,
        ts: float,
        channel: str | None,
        sa: int,
        pgn: int,
        entry: tuple[str, Callable[[bytes], JSONObject]],
        data: bytes,
    ) -> list[Record]:
        name, decoder = entry
        key = (pgn, data)
        cached = self._cache.get(key)
        if cached is None:
            cached = decoder(data)
            if len(self._cache) >= _CACHE_LIMIT:
                self._cache.clear()
            self._cache[key] = cached
        # Records own their fields: copy, so a consumer's change cannot leak into the cache.
        fields = _copy_fields(cached) if name == "dm1" else cached.copy()
        return self._record(ts, channel, sa, pgn, name, fields)

    def _record(
        self,
        ts: float,
        channel: str | None,
        sa: int,
        pgn: int,
        name: str,
        fields: JSONObject,
        *,
        from_transfer: bool = False,
    ) -> list[Record]:
        stats = self.stats
        if not from_transfer:
            stats.decoded_frames += 1
        series = fields.get("series")
        if name in ("component_id", "software_id") and series and isinstance(series, int):
            self._series[(channel, sa)] = series
        if self._only is not None and name not in self._only:
            return []
        stats.records += 1
        stats.by_name[name] = stats.by_name.get(name, 0) + 1
        return [Record(ts, channel, sa, pgn, name, fields)]

    def _transport(
        self, ts: float, channel: str | None, sa: int, da: int, pgn: int, data: bytes
    ) -> list[Record]:
        stats = self.stats
        transfer: Transfer | None
        if da == GLOBAL_ADDRESS:
            transfer = self._bam.feed(ts, channel, sa, da, pgn, data)
        else:
            # A connection-mode transfer to one node (the gateway, or any other).
            transfer = self._rts.feed(ts, channel, sa, da, pgn, data)
        self._sync_transfer_stats()
        stats.transport_frames += 1
        if transfer is None:
            return []
        if transfer.pgn not in _TRANSPORTED:
            return []
        payload = transfer.payload
        try:
            if transfer.pgn == PGN_DM1:
                name, fields = "dm1", decode_dm1(payload)
            elif transfer.pgn == PGN_COMPONENT_ID:
                name, fields = "component_id", decode_component_id(payload)
            else:
                name, fields = "software_id", decode_software_id(payload)
        except DecodeError:
            self._bad_payloads += 1
            self._sync_transfer_stats()
            return []
        return self._record(
            transfer.ts, channel, sa, transfer.pgn, name, fields, from_transfer=True
        )

    def _sync_transfer_stats(self) -> None:
        bam, rts = self._bam.stats, self._rts.stats
        self.stats.transfers_completed = bam.completed + rts.completed - self._bad_payloads
        self.stats.transfers_incomplete = bam.incomplete + rts.incomplete
        self.stats.transfers_broken = bam.broken + rts.broken + self._bad_payloads

    def finish(self, now: float | None = None) -> None:
        """End of input: transfers still open are incomplete."""
        until = float("inf") if now is None else now
        self._bam.expire(until)
        self._rts.expire(until)
        self._sync_transfer_stats()
