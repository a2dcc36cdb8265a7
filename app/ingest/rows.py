"""The rows the ingest hands to the writer: one named type per kind of row.

The pipeline builds them, the writer groups them into a `eqgw.store.writes.Batch`, and the
journal keeps them on disk while the database is away. On disk a row is the plain tuple
`(kind, key, payload)` of `as_tuple()` (the journal reads plain data only, and a journal
written by an earlier version replays unchanged); `from_tuple` reads it back.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import StrEnum
from typing import ClassVar, Literal, cast

from eqgw.store.writes import (
    BatteryValues,
    Dm1Values,
    EpisodeKey,
    EpisodeValues,
    LiveKey,
    LiveValues,
    MeasurementValues,
    MessageValues,
    RawFrameValues,
    StatusValues,
    UnitInfo,
    UnitKey,
    VehicleInfo,
)


class RowKind(StrEnum):
    """What a row is; its value is the row's name in the journal."""

    VEHICLE = "vehicle"
    UNIT = "unit"
    UNIT_INFO = "unit_info"
    UNIT_OWNER = "unit_owner"
    SEEN = "seen"
    MEASUREMENTS = "measurements"
    BATTERY_STATES = "battery_states"
    STATUS_CHANGES = "status_changes"
    DM1_SNAPSHOTS = "dm1_snapshots"
    MESSAGES = "messages"
    RAW_FRAMES = "raw_frames"
    EPISODE = "episode"
    LIVE = "live"


@dataclass(slots=True)
class VehicleRow:
    """A vehicle the units being written belong to (inserted if new)."""

    vehicle_id: str
    info: VehicleInfo
    kind: ClassVar[Literal[RowKind.VEHICLE]] = RowKind.VEHICLE

    def as_tuple(self) -> tuple[str, str, VehicleInfo]:
        return (self.kind.value, self.vehicle_id, self.info)


@dataclass(slots=True)
class UnitRow:
    """A unit and its vehicle: the writer learns (or creates) its id."""

    key: UnitKey
    vehicle_id: str
    kind: ClassVar[Literal[RowKind.UNIT]] = RowKind.UNIT

    def as_tuple(self) -> tuple[str, UnitKey, str]:
        return (self.kind.value, self.key, self.vehicle_id)


@dataclass(slots=True)
class UnitInfoRow:
    """A unit's identification (series, model, software ID) as learned at `info["ts"]`."""

    key: UnitKey
    info: UnitInfo
    kind: ClassVar[Literal[RowKind.UNIT_INFO]] = RowKind.UNIT_INFO

    def as_tuple(self) -> tuple[str, UnitKey, UnitInfo]:
        return (self.kind.value, self.key, self.info)


@dataclass(slots=True)
class UnitOwnerRow:
    """A NAME took the unit's address at `since` (J1939 address claim)."""

    key: UnitKey
    since: float
    name: str
    kind: ClassVar[Literal[RowKind.UNIT_OWNER]] = RowKind.UNIT_OWNER

    def as_tuple(self) -> tuple[str, UnitKey, dict[str, float | str]]:
        return (self.kind.value, self.key, {"since": self.since, "name": self.name})


@dataclass(slots=True)
class SeenRow:
    """The span of frame times a unit was heard in since the last hand-over."""

    key: UnitKey
    first: float
    last: float
    kind: ClassVar[Literal[RowKind.SEEN]] = RowKind.SEEN

    def as_tuple(self) -> tuple[str, UnitKey, tuple[float, float]]:
        return (self.kind.value, self.key, (self.first, self.last))


@dataclass(slots=True)
class MeasurementRow:
    """One row of `measurements` (voltages and currents)."""

    key: UnitKey
    values: MeasurementValues
    kind: ClassVar[Literal[RowKind.MEASUREMENTS]] = RowKind.MEASUREMENTS

    def as_tuple(self) -> tuple[str, UnitKey, MeasurementValues]:
        return (self.kind.value, self.key, self.values)


@dataclass(slots=True)
class BatteryStateRow:
    """One row of `battery_states`."""

    key: UnitKey
    values: BatteryValues
    kind: ClassVar[Literal[RowKind.BATTERY_STATES]] = RowKind.BATTERY_STATES

    def as_tuple(self) -> tuple[str, UnitKey, BatteryValues]:
        return (self.kind.value, self.key, self.values)


@dataclass(slots=True)
class StatusChangeRow:
    """One row of `status_changes` (the flags when any changed)."""

    key: UnitKey
    values: StatusValues
    kind: ClassVar[Literal[RowKind.STATUS_CHANGES]] = RowKind.STATUS_CHANGES

    def as_tuple(self) -> tuple[str, UnitKey, StatusValues]:
        return (self.kind.value, self.key, self.values)


@dataclass(slots=True)
class Dm1SnapshotRow:
    """One row of `dm1_snapshots` (a DM1 whose content changed)."""

    key: UnitKey
    values: Dm1Values
    kind: ClassVar[Literal[RowKind.DM1_SNAPSHOTS]] = RowKind.DM1_SNAPSHOTS

    def as_tuple(self) -> tuple[str, UnitKey, Dm1Values]:
        return (self.kind.value, self.key, self.values)


@dataclass(slots=True)
class MessageRow:
    """One row of `messages` (every other record: identification, control, parameters...)."""

    key: UnitKey
    values: MessageValues
    kind: ClassVar[Literal[RowKind.MESSAGES]] = RowKind.MESSAGES

    def as_tuple(self) -> tuple[str, UnitKey, MessageValues]:
        return (self.kind.value, self.key, self.values)


@dataclass(slots=True)
class RawFrameRow:
    """One frame for the raw archive (`eqgw.store.archive`)."""

    key: UnitKey
    values: RawFrameValues
    kind: ClassVar[Literal[RowKind.RAW_FRAMES]] = RowKind.RAW_FRAMES

    def as_tuple(self) -> tuple[str, UnitKey, RawFrameValues]:
        return (self.kind.value, self.key, self.values)


@dataclass(slots=True)
class EpisodeRow:
    """A fault episode's state after a change (the latest of one episode wins)."""

    key: EpisodeKey
    values: EpisodeValues
    kind: ClassVar[Literal[RowKind.EPISODE]] = RowKind.EPISODE

    def as_tuple(self) -> tuple[str, EpisodeKey, EpisodeValues]:
        return (self.kind.value, self.key, self.values)


@dataclass(slots=True)
class LiveRow:
    """A unit's latest value of one live slot (the newest of one slot wins)."""

    key: LiveKey
    values: LiveValues
    kind: ClassVar[Literal[RowKind.LIVE]] = RowKind.LIVE

    def as_tuple(self) -> tuple[str, LiveKey, LiveValues]:
        return (self.kind.value, self.key, self.values)


Row = (
    VehicleRow
    | UnitRow
    | UnitInfoRow
    | UnitOwnerRow
    | SeenRow
    | MeasurementRow
    | BatteryStateRow
    | StatusChangeRow
    | Dm1SnapshotRow
    | MessageRow
    | RawFrameRow
    | EpisodeRow
    | LiveRow
)
# A row as stored in the journal: (kind, key, payload) of plain data.
RowTuple = tuple[str, object, object]


def _unit_key(key: object) -> UnitKey:
    match key:
        case (str() as bus, int() as sa):
            return (bus, sa)
    raise ValueError(f"not a unit key: {key!r}")


def _object(payload: object) -> dict[str, object]:
    if not isinstance(payload, dict):
        raise ValueError(f"not a row's values: {payload!r}")
    return payload


def from_tuple(item: object) -> Row:
    """The row an `as_tuple()` tuple (a journal's entry) holds; ValueError if it is none.
    Keys are checked; values are taken as written (the journal reads plain data only)."""
    match item:
        case (str() as kind, key, payload):
            pass
        case _:
            raise ValueError(f"not a row: {item!r}")
    match kind:
        case RowKind.MEASUREMENTS:
            return MeasurementRow(_unit_key(key), cast(MeasurementValues, _object(payload)))
        case RowKind.RAW_FRAMES:
            return RawFrameRow(_unit_key(key), cast(RawFrameValues, _object(payload)))
        case RowKind.BATTERY_STATES:
            return BatteryStateRow(_unit_key(key), cast(BatteryValues, _object(payload)))
        case RowKind.STATUS_CHANGES:
            return StatusChangeRow(_unit_key(key), cast(StatusValues, _object(payload)))
        case RowKind.DM1_SNAPSHOTS:
            return Dm1SnapshotRow(_unit_key(key), cast(Dm1Values, _object(payload)))
        case RowKind.MESSAGES:
            return MessageRow(_unit_key(key), cast(MessageValues, _object(payload)))
        case RowKind.LIVE:
            match key:
                case (unit, str() as slot):
                    return LiveRow((_unit_key(unit), slot), cast(LiveValues, _object(payload)))
        case RowKind.EPISODE:
            match key:
                case (unit, str() as fault, float() | int() as started_at):
                    values = cast(EpisodeValues, _object(payload))
                    return EpisodeRow((_unit_key(unit), fault, started_at), values)
        case RowKind.SEEN:
            match payload:
                case (float() | int() as first, float() | int() as last):
                    return SeenRow(_unit_key(key), first, last)
        case RowKind.UNIT:
            if isinstance(payload, str):
                return UnitRow(_unit_key(key), payload)
        case RowKind.UNIT_INFO:
            return UnitInfoRow(_unit_key(key), cast(UnitInfo, _object(payload)))
        case RowKind.UNIT_OWNER:
            match _object(payload):
                case {"since": float() | int() as since, "name": str() as name}:
                    return UnitOwnerRow(_unit_key(key), since, name)
        case RowKind.VEHICLE:
            if isinstance(key, str):
                return VehicleRow(key, cast(VehicleInfo, _object(payload)))
        case _:
            raise ValueError(f"unknown row kind {kind!r}")
    raise ValueError(f"malformed {kind} row: {item!r}")
