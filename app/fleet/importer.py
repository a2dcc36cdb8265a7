"""The fleet as CSV: one row per bus (a vehicle without a bus: one row with no bus), read into
vehicle specifications with every bad row's line number and reason, and written back.

Columns (the header names them; any order; only `vehicle_id` is required):

    vehicle_id, name, depot, bus, interface, channel, bitrate, equalizer_sas, gateway_sa,
    request_byte_order, address_claim, address_claim_name, stall_after_s, options,
    options.<NAME>

A vehicle's rows give its name and depot once (the first row that has them; another value on a
later row is an error) and each of its buses on a row of its own. `equalizer_sas` is a list of
addresses separated by spaces or `;` (`30 31`), numbers are decimal or `0x` hex, `bitrate`
`none` is no bitrate, `address_claim` is true or false, `options` a JSON object and each
`options.NAME` column one option (a JSON number, true, false, or else text). An empty cell is
the default, as a key left out of the fleet file is. Every value is then checked exactly as the
fleet file's are (eqgw.config.VehicleConfig, eqgw.bus.config.BusConfig).
"""

from __future__ import annotations

import csv
import io
import json
from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Any

from pydantic import ValidationError

from eqgw.bus.config import BusConfig
from eqgw.config import VehicleConfig
from eqgw.fleet.registry import Edit, Fleet, Problem, VehicleSpec, reasons

VEHICLE_COLUMNS = ("vehicle_id", "name", "depot")
BUS_COLUMNS = (
    "bus",
    "interface",
    "channel",
    "bitrate",
    "equalizer_sas",
    "gateway_sa",
    "request_byte_order",
    "address_claim",
    "address_claim_name",
    "stall_after_s",
    "options",
)
COLUMNS = (*VEHICLE_COLUMNS, *BUS_COLUMNS)
OPTION_PREFIX = "options."
MAX_ROWS = 100_000


class CsvError(ValueError):
    """A value of a cell that cannot be read (the reason names the column)."""


def _int(column: str, text: str) -> int:
    try:
        return int(text.replace("_", ""), 0)
    except ValueError:
        raise CsvError(f"{column}: {text!r} is not a whole number") from None


def _float(column: str, text: str) -> float:
    try:
        return float(text)
    except ValueError:
        raise CsvError(f"{column}: {text!r} is not a number") from None


def _bool(column: str, text: str) -> bool:
    low = text.lower()
    if low in ("true", "yes", "1", "on"):
        return True
    if low in ("false", "no", "0", "off"):
        return False
    raise CsvError(f"{column}: {text!r} is not true or false")


def _sas(column: str, text: str) -> list[int]:
    parts = text.replace(";", " ").replace(",", " ").split()
    return [_int(column, p) for p in parts]


def _options(column: str, text: str) -> dict[str, Any]:
    try:
        value = json.loads(text)
    except ValueError:
        raise CsvError(f"{column}: not a JSON object ({text[:60]!r})") from None
    if not isinstance(value, dict):
        raise CsvError(f"{column}: not a JSON object ({text[:60]!r})")
    return value


def _option_value(text: str) -> Any:
    try:
        value = json.loads(text)
    except ValueError:
        return text
    return value if isinstance(value, int | float | bool) else text


_READERS = {
    "bitrate": lambda c, t: None if t.lower() == "none" else _int(c, t),
    "equalizer_sas": _sas,
    "gateway_sa": _int,
    "address_claim": _bool,
    "stall_after_s": _float,
    "options": _options,
}


@dataclass(slots=True)
class _Vehicle:
    line: int
    name: str | None
    depot: str | None
    name_line: int | None
    depot_line: int | None
    buses: list[BusConfig] = field(default_factory=list)
    bus_lines: dict[str, int] = field(default_factory=dict)


def parse(text: str) -> Edit:
    """The vehicles of a CSV file (its text) as an edit of the fleet: every vehicle it names,
    whole, and every bad row as a problem with its line number (line 1 is the header)."""
    problems: list[Problem] = []
    if text.startswith("\ufeff"):
        text = text[1:]
    reader = csv.reader(io.StringIO(text, newline=""), strict=True)
    try:
        header = next(reader)
    except StopIteration:
        return Edit(problems=[Problem("the file is empty: a header line is needed", line=1)])
    except csv.Error as exc:
        return Edit(problems=[Problem(f"unreadable CSV: {exc}", line=1)])
    columns = [h.strip().lower() for h in header]
    unknown = [c for c in columns if c not in COLUMNS and not c.startswith(OPTION_PREFIX)]
    if unknown:
        known = ", ".join(COLUMNS)
        problems.append(
            Problem(
                f"unknown column(s) {', '.join(unknown)}; the columns are {known}, options.NAME",
                line=1,
            )
        )
    if "vehicle_id" not in columns:
        problems.append(Problem("the header has no vehicle_id column", line=1))
    dupes = sorted({c for c in columns if columns.count(c) > 1})
    if dupes:
        problems.append(Problem(f"column(s) given twice: {', '.join(dupes)}", line=1))
    if problems:
        return Edit(problems=problems)
    vehicles: dict[str, _Vehicle] = {}
    bus_lines: dict[str, int] = {}  # every bus name of the file: its line
    last = reader.line_num
    rows = 0
    while True:
        try:
            cells = next(reader)
        except StopIteration:
            break
        except csv.Error as exc:
            problems.append(Problem(f"unreadable CSV: {exc}", line=last + 1))
            break
        line, last = last + 1, reader.line_num
        if not any(c.strip() for c in cells):
            continue
        rows += 1
        if rows > MAX_ROWS:
            problems.append(Problem(f"more than {MAX_ROWS} rows", line=line))
            break
        if len(cells) != len(columns):
            problems.append(
                Problem(f"{len(cells)} cells where the header has {len(columns)}", line=line)
            )
            continue
        row = {c: v.strip() for c, v in zip(columns, cells, strict=True)}
        problem = _row(row, line, vehicles, bus_lines)
        if problem is not None:
            problems.append(problem)
    # A vehicle with a bad row is left out whole (the file does not say what it is to be).
    bad = {p.vehicle_id for p in problems if p.vehicle_id}
    specs = []
    for vid, v in vehicles.items():
        if vid in bad:
            continue
        cfg = VehicleConfig.model_construct(id=vid, name=v.name, depot=v.depot)
        specs.append(VehicleSpec(cfg, v.buses, v.line, v.bus_lines))
    return Edit(specs=specs, problems=problems)


def _row(
    row: dict[str, str], line: int, vehicles: dict[str, _Vehicle], bus_lines: dict[str, int]
) -> Problem | None:
    """Take one row into `vehicles`; the row's problem, if it has one."""
    vid = row["vehicle_id"]
    name = row.get("name") or None
    depot = row.get("depot") or None
    try:
        checked = VehicleConfig(id=vid, name=name, depot=depot)
    except ValidationError as exc:
        return Problem(reasons(exc), line=line, vehicle_id=vid or None)
    v = vehicles.get(vid)
    if v is None:
        v = vehicles[vid] = _Vehicle(
            line, checked.name, checked.depot, line if name else None, line if depot else None
        )
    else:
        for what, value, have, at in (
            ("name", name, v.name, v.name_line),
            ("depot", depot, v.depot, v.depot_line),
        ):
            if value is None:
                continue
            if have is None:
                setattr(v, what, value)
                setattr(v, f"{what}_line", line)
            elif have != value:
                return Problem(
                    f"{what} {value!r} differs from {have!r} on line {at} (a vehicle has one)",
                    line=line,
                    vehicle_id=vid,
                )
    bus_cells = {c: t for c, t in row.items() if c in BUS_COLUMNS or c.startswith(OPTION_PREFIX)}
    if not row.get("bus"):
        given = sorted(c for c, t in bus_cells.items() if t)
        if given:
            return Problem(
                f"{', '.join(given)} given without a bus name (the bus column)",
                line=line,
                vehicle_id=vid,
            )
        return None
    try:
        values = _bus_values(bus_cells)
    except CsvError as exc:
        return Problem(str(exc), line=line, vehicle_id=vid)
    try:
        bus = BusConfig.model_validate({**values, "vehicle_id": vid})
    except ValidationError as exc:
        return Problem(reasons(exc), line=line, vehicle_id=vid)
    if bus.name in bus_lines:
        return Problem(
            f"bus {bus.name!r} is given twice (line {bus_lines[bus.name]})",
            line=line,
            vehicle_id=vid,
        )
    bus_lines[bus.name] = line
    v.buses.append(bus)
    v.bus_lines[bus.name] = line
    return None


def _bus_values(cells: dict[str, str]) -> dict[str, Any]:
    values: dict[str, Any] = {}
    options: dict[str, Any] = {}
    for column, text in cells.items():
        if not text:
            continue
        if column.startswith(OPTION_PREFIX):
            key = column[len(OPTION_PREFIX) :]
            options[key] = _option_value(text)
        elif column == "bus":
            values["name"] = text
        elif column in _READERS:
            values[column] = _READERS[column](column, text)
        else:
            values[column] = text
    if options:
        values["options"] = {**values.get("options", {}), **options}
    return values


def _cell(value: Any) -> str:
    if value is None:
        return ""
    if isinstance(value, bool):
        return "true" if value else "false"
    return str(value)


def write(fleet: Fleet, only: Iterable[str] | None = None) -> str:
    """The fleet (or the vehicles `only`) as CSV an import reads back as it is."""
    out = io.StringIO()
    w = csv.writer(out, lineterminator="\n")
    w.writerow(COLUMNS)
    wanted = None if only is None else set(only)
    for vid, v in sorted(fleet.vehicles.items()):
        if wanted is not None and vid not in wanted:
            continue
        head = [vid, "" if v.name in (None, vid) else v.name, v.depot or ""]
        buses = sorted(fleet.buses_of(vid), key=lambda b: b.name)
        if not buses:
            w.writerow([*head, *[""] * len(BUS_COLUMNS)])
        for b in buses:
            claim = b.address_claim_name
            w.writerow(
                [
                    *head,
                    b.name,
                    b.interface,
                    b.channel,
                    "none" if b.bitrate is None else str(b.bitrate),
                    " ".join(str(sa) for sa in b.equalizer_sas),
                    str(b.gateway_sa),
                    b.request_byte_order,
                    _cell(b.address_claim),
                    "" if claim is None else f"0x{claim:016X}",
                    f"{b.stall_after_s:g}",
                    json.dumps(b.options, separators=(",", ":")) if b.options else "",
                ]
            )
    return out.getvalue()
