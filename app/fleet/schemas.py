"""Request and response bodies of the fleet's management routes (`management.py`), and the
answers of its read routes (`endpoints.py`: the listing, a vehicle's live values, history,
status changes and faults).

A vehicle and its buses are checked by the very classes that check the fleet file's
(eqgw.config.VehicleConfig, eqgw.bus.config.BusConfig): the bodies inherit them. The read
routes render their bodies themselves (orjson, cached listings), so FastAPI does not validate
them on the way out: those models are what the OpenAPI document promises, and what the
contract test (tests/test_api_schemathesis.py) checks every answer against.
"""

from __future__ import annotations

from typing import Any, Literal

from pydantic import BaseModel, Field

from eqgw.bus.config import BusConfig
from eqgw.config import VehicleConfig
from eqgw.web.schemas import RequestBody

# The most buses one vehicle may have (a vehicle has a few).
MAX_BUSES = 64


class BusIn(RequestBody, BusConfig):
    """A bus of the vehicle, as a `[[buses]]` entry of the fleet file."""

    # The vehicle's own id, or left out (a body is about one vehicle).
    vehicle_id: str | None = Field(  # type: ignore[assignment]
        default=None, max_length=64, description="the vehicle's id (may be left out)"
    )


class VehicleCreate(RequestBody, VehicleConfig):
    """A new vehicle and its buses."""

    buses: list[BusIn] = Field(
        default_factory=list,
        max_length=MAX_BUSES,
        description="its CAN buses (none: a vehicle known to the fleet, read by no gateway, "
        "e.g. one whose frames a forwarder uploads)",
    )


class VehiclePatch(RequestBody):
    """What changes of a vehicle: fields left out stay as they are; `buses`, when given, is
    the complete list (a bus left out is closed and removed, one changed is reopened)."""

    name: str | None = Field(default=None, max_length=200, description="null: the id")
    depot: str | None = Field(default=None, max_length=200, description="null: no depot")
    buses: list[BusIn] | None = Field(default=None, max_length=MAX_BUSES)


class BusOut(BaseModel):
    """A bus of a vehicle as the fleet holds it."""

    name: str
    interface: str
    channel: str
    bitrate: int | None
    options: dict[str, Any]
    equalizer_sas: list[int]
    gateway_sa: int
    request_byte_order: str
    address_claim: bool
    address_claim_name: str | None = Field(
        description="the bus's own J1939 NAME (0x hex), or null: derived from [address_claim]"
    )
    stall_after_s: float


class VehicleOut(BaseModel):
    """A vehicle as the fleet holds it, with its buses."""

    id: str
    name: str
    depot: str | None
    buses: list[BusOut]
    version: int = Field(description="the fleet's version this answer is of")


class ImportRow(BaseModel):
    """A vehicle an import adds, changes or removes."""

    id: str
    line: int | None = Field(description="its first line in the file")
    fields: list[str] | None = Field(
        default=None, description="changed: which of name, depot, buses"
    )
    buses_added: list[str] | None = None
    buses_changed: list[str] | None = None
    buses_removed: list[str] | None = None


class BadRow(BaseModel):
    """A bad row: its line (1 is the header) and why."""

    line: int | None
    vehicle_id: str | None
    reason: str


class ImportReport(BaseModel):
    """What an import did or, in a dry run, would do."""

    dry_run: bool
    applied: bool = Field(description="whether the fleet was changed")
    mode: str = Field(description="merge or replace")
    version: int = Field(description="the fleet's version after it (before, when not applied)")
    added: list[ImportRow]
    changed: list[ImportRow]
    unchanged: list[str] = Field(description="vehicles of the file the fleet has as they are")
    removed: list[ImportRow] = Field(
        description="replace: vehicles in the caller's scope the file leaves out"
    )
    untouched: list[str] = Field(
        description="merge: vehicles in the caller's scope the file leaves out (kept)"
    )
    bad_rows: list[BadRow] = Field(description="every bad row; any: nothing was changed")


class ImportRefused(BaseModel):
    """A refused import: `bad_rows` lists every bad row (line, reason) and nothing was
    changed; the rest of the report says what the good rows would do. A request refused
    before the file is read (a bad query parameter) has `type` and `detail` only."""

    type: str
    detail: str
    bad_rows: list[BadRow] | None = None
    dry_run: bool | None = None
    applied: bool | None = None
    mode: str | None = None
    version: int | None = None
    added: list[ImportRow] | None = None
    changed: list[ImportRow] | None = None
    unchanged: list[str] | None = None
    removed: list[ImportRow] | None = None
    untouched: list[str] | None = None


# -- the read routes' answers (endpoints.py) ------------------------------------------------------


class FaultSummary(BaseModel):
    """An open fault of a unit, in a listing."""

    fault: str = Field(description="OVF, UVF, IMB, EQFLT, SPN<n>/FMI<m>, ...")
    state: str = Field(description="active or stale")
    occurrence_count: int | None = Field(description="the unit's DM1 occurrence count")


class ShortDiagnosis(BaseModel):
    """The troubleshooting condition of a unit and its sentence."""

    condition: str = Field(
        description="standby, normal, overload, equalizer_not_functioning, abnormal, "
        "shutdown_risk or unknown"
    )
    text: str


class Diagnosis(ShortDiagnosis):
    """The troubleshooting row with the numbers it was made from."""

    battery_a_v: float | None = None
    battery_b_v: float | None = None
    system_v: float | None = None
    b_minus_a_v: float | None = None
    running: bool | None = None
    shutdown_flag: bool | None = None


_UNIT_STATE = (
    "online; offline (silent while its bus carries traffic: the `offline` alert); parked "
    "(silent with its whole bus, ignition off: no alert)"
)
_VEHICLE_STATE = (
    "not_reporting (no unit heard for monitor.not_reporting_after_s, or never), parked (every "
    "bus of the vehicle silent), offline (a unit silent while its bus carries traffic), "
    "attention (a fault open), ok"
)


class VehicleState(BaseModel):
    """A vehicle's state and when it was last heard."""

    state: Literal["ok", "attention", "offline", "parked", "not_reporting"] = Field(
        description=_VEHICLE_STATE
    )
    last_heard: float | None = Field(
        description="its units' latest frame (epoch seconds), null when never heard"
    )
    parked_since: float | None = Field(
        description="parked: when its bus fell silent (epoch seconds)"
    )


class UnitSummary(BaseModel):
    """One unit's live summary."""

    unit: int = Field(description="the unit's J1939 source address")
    bus: str
    name: str | None = Field(
        default=None,
        description="J1939 NAME (hex) of the node holding the address, from its address "
        "claim; null when no claim was seen",
    )
    series: int | None = Field(description="70 or 80 once identified")
    model: str | None
    online: bool
    state: Literal["online", "offline", "parked"] = Field(description=_UNIT_STATE)
    last_seen: float | None = Field(description="epoch seconds")
    parked_since: float | None = Field(
        description="parked: when its bus fell silent (epoch seconds)"
    )
    v12: float | None
    v24: float | None
    imbalance_v: float | None = Field(description="(v24 - v12) - v12")
    soc_12v: float | None
    soc_24v: float | None
    soh_12v: float | None
    soh_24v: float | None
    active_faults: list[str]
    faults: list[FaultSummary]
    diagnosis: ShortDiagnosis


class VehicleSummary(VehicleState):
    """A vehicle, its state and its units."""

    id: str
    name: str | None
    depot: str | None
    online: bool = Field(description="some unit of the vehicle is online")
    units: list[UnitSummary]


class VehicleList(BaseModel):
    """The fleet."""

    vehicles: list[VehicleSummary] = Field(description="the page asked for, ordered by id")
    ts: float = Field(description="when the listing was made (epoch seconds)")
    total: int = Field(description="vehicles matching the filters, on every page")
    offset: int = Field(description="vehicles skipped before this page")
    limit: int | None = Field(description="the page size asked for; null: every vehicle")
    counts: dict[str, int] | None = Field(
        default=None,
        description="with a filter or paging: vehicles per state among those matching depot "
        "and search (the state filter aside)",
    )


class LatestValue(BaseModel):
    """The latest decoded fields of one message (slot) of a unit."""

    ts: float
    fields: dict[str, Any]


class Episode(BaseModel):
    """One continuous period of one fault on one unit."""

    fault: str
    spn: int | None = None
    fmi: int | None = None
    source: str = Field(description="dm1, status, dm1+status or monitor")
    state: str = Field(description="active, stale or closed")
    started_at: float
    last_seen_at: float
    ended_at: float | None = None
    ended_by: str | None = None
    occurrence_count: int | None = None


class StoredEpisode(Episode):
    """A fault episode from the database, with its unit."""

    id: int
    unit_id: int
    vehicle_id: str
    bus: str
    sa: int


class UnitLive(BaseModel):
    """Everything known now about one unit."""

    vehicle_id: str
    bus: str
    sa: int
    unit: int = Field(description="the source address again (the listing's name for it)")
    name: str | None = Field(
        default=None,
        description="J1939 NAME (hex) of the node holding the address, from its address "
        "claim; null when no claim was seen",
    )
    series: int | None
    model: str | None
    software_id: str | None
    first_seen: float | None
    last_seen: float | None
    online: bool
    state: Literal["online", "offline", "parked"] = Field(description=_UNIT_STATE)
    parked_since: float | None = Field(
        description="parked: when its bus fell silent (epoch seconds)"
    )
    latest: dict[str, LatestValue] = Field(description="by slot: status, voltages, ...")
    faults: list[Episode]
    status_flags: dict[str, str] = Field(description="flag name: active, inactive, ...")
    summary: UnitSummary
    diagnosis: Diagnosis


class VehicleLive(VehicleState):
    """A vehicle's live view."""

    id: str
    name: str | None
    depot: str | None
    units: list[UnitLive]


class Point(BaseModel):
    """One point of a series: a bucket's aggregate, or a raw value (bucket `raw`)."""

    ts: float = Field(description="bucket start or sample time (epoch seconds)")
    value: float | None = Field(default=None, description="raw samples only")
    count: int | None = Field(default=None, description="buckets only")
    min: float | None = None
    max: float | None = None
    avg: float | None = None


class Owner(BaseModel):
    """A period one NAME held the unit's address (the first claim seen, or a change of
    owner, to the next change)."""

    name: str = Field(description="J1939 NAME (hex)")
    from_: float = Field(alias="from", description="when it took the address (epoch seconds)")
    to: float | None = Field(description="when another NAME took it; null: holds it still")


class History(BaseModel):
    """Time series of one unit."""

    vehicle_id: str
    unit: int
    bus: str
    from_: float = Field(alias="from")
    to: float
    bucket: str = Field(description="raw, 1m, 15m, 1h or 1d")
    name: str | None = Field(
        default=None,
        description="J1939 NAME (hex) holding the address now; null when no claim was seen",
    )
    owners: list[Owner] = Field(
        default_factory=list,
        description="the NAMEs that held the address during the range, oldest first: which "
        "node each part of the series is from (empty when no claim was seen)",
    )
    series: dict[str, list[Point]] = Field(description="by field name")


class StatusChange(BaseModel):
    """The status flags after a change, and which changed."""

    ts: float
    flags: dict[str, str]
    changed: list[str]


class StatusHistory(BaseModel):
    """Status-flag changes of one unit, oldest first."""

    vehicle_id: str
    unit: int
    from_: float = Field(alias="from")
    to: float
    changes: list[StatusChange]


class FaultCount(BaseModel):
    """Per fault: episodes, how many are open, and the unit's occurrence count."""

    episodes: int
    active: int
    occurrence_count: int | None


class FaultList(BaseModel):
    """Fault episodes (newest first) and counts over all of them."""

    episodes: list[StoredEpisode]
    counts: dict[str, FaultCount]
    total: int
    truncated: bool = Field(description="more episodes than listed (counts cover all)")
