"""Request and response bodies of the fleet's management routes. A vehicle and its buses are
checked by the very classes that check the fleet file's (eqgw.config.VehicleConfig,
eqgw.bus.config.BusConfig): the bodies inherit them."""

from __future__ import annotations

from typing import Any

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
