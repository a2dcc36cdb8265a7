"""Submission checks: why a command is refused before it is queued, and what it carries.

The payload of each kind checked against every unit it reaches, the conflicts between two
pending commands, an Idempotency-Key replay. What a unit reaches and whether it is online
need the live state: `CommandService` checks those."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

from eqgw.commands.model import AffectedUnit, Command, CommandKind, CommandPayload, Json
from eqgw.ingest.state import UnitState
from eqgw.protocol.j1939 import (
    PGN_COMPONENT_ID,
    PGN_DM1,
    PGN_SOFTWARE_ID,
)
from eqgw.protocol.params import FACTORY_RESET, validate_parameter_write

# API field -> (control signal, status flag that confirms it).
CONTROL_FIELDS: dict[str, tuple[str, str]] = {
    "jump_start_override": ("can_jso", "state_can_jso"),
    "can_onoff_enable": ("can_onoff_en", "state_onoff_en"),
    "equalizer_on": ("can_eq_onoff", "eq_state_onoff"),
    "smart_sensor_messages": ("can_ss_msg_en", "can_ss_msg_on"),
}
# What a unit can be asked for -> (requested PGN, live slot of the answer).
REQUESTS: dict[str, tuple[int, str]] = {
    "dm1": (PGN_DM1, "dm1"),
    "component_id": (PGN_COMPONENT_ID, "component_id"),
    "software_id": (PGN_SOFTWARE_ID, "software_id"),
}


# Parameter writes that put every parameter of the unit back (index 0): they conflict with
# any other parameter write pending for the unit.
RESET_PARAMETERS = frozenset({FACTORY_RESET, "profile"})


class CommandRefused(Exception):
    """A command that must not be queued: HTTP status, stable type, reason."""

    def __init__(self, status: int, type_: str, detail: str, **extra: object) -> None:
        super().__init__(detail)
        self.status = status
        self.type = type_
        self.detail = detail
        self.extra = extra


@dataclass(slots=True)
class Submitter:
    """Who submits: the key (None for internal use)."""

    key_id: int | None
    key_name: str | None


def _series_text(series: int | None) -> str:
    return "an unknown series" if series is None else f"the {series}-series"


def affected_units(on_bus: list[tuple[int, UnitState | None]]) -> list[AffectedUnit]:
    """The units a command reaches, as the API shows them: SA and series (None: unknown)."""
    return [{"sa": sa, "series": st.series if st is not None else None} for sa, st in on_bus]


def _replayed(earlier: Command, kind: str, vehicle_id: str, body: Mapping[str, Json]) -> Command:
    """The command made earlier with this Idempotency-Key, if the request is the same."""
    if (
        earlier.kind != kind
        or earlier.vehicle_id != vehicle_id
        or dict(earlier.payload.get("request", {})) != dict(body)
    ):
        raise CommandRefused(
            422,
            "idempotency_key_reused",
            "this Idempotency-Key was used for a different request",
            command_id=earlier.id,
        )
    return earlier


def control_payload(units: list[UnitState], body: Mapping[str, Json]) -> CommandPayload:
    """Control fields checked against every unit on the bus (each one acts on them)."""
    wanted = {k: body[k] for k in CONTROL_FIELDS if body.get(k) is not None}
    if not wanted:
        raise CommandRefused(422, "empty_command", "no control field given: nothing to do")
    if "smart_sensor_messages" in wanted:
        _check_smart_sensor_messages(units)
    if "equalizer_on" in wanted:
        _check_equalizer_on(units, wanted.get("can_onoff_enable"))
    fields = {CONTROL_FIELDS[k][0]: ("enable" if v else "disable") for k, v in wanted.items()}
    expect = {CONTROL_FIELDS[k][1]: ("active" if v else "inactive") for k, v in wanted.items()}
    return {"request": dict(body), "fields": fields, "expect": expect}


def _check_smart_sensor_messages(units: list[UnitState]) -> None:
    """Refuse smart_sensor_messages unless every unit is of the 70-series."""
    others = [u for u in units if u.series != 70]
    if not others:
        return
    if len(units) == 1:
        series = _series_text(others[0].series)
        which = f"this unit is {series}"
    else:
        which = "it reaches " + ", ".join(
            f"unit {u.ref.sa} ({_series_text(u.series)})" for u in others
        )
    raise CommandRefused(
        422,
        "unsupported_field",
        f"smart_sensor_messages exists only on the 70-series; {which}",
    )


def _check_equalizer_on(units: list[UnitState], enable: Json) -> None:
    """Refuse equalizer_on when the command disables CAN on/off, or when it leaves it alone
    and a unit does not have it enabled."""
    if enable is False:
        raise CommandRefused(
            422,
            "contradictory",
            "equalizer_on needs CAN on/off enabled; this command disables it",
        )
    off = [u for u in units if (u.status_flags or {}).get("state_onoff_en") != "active"]
    if enable is None and off:
        which = (
            "it is not"
            if len(units) == 1
            else "on unit " + ", ".join(str(u.ref.sa) for u in off) + " it is not"
        )
        raise CommandRefused(
            409,
            "onoff_not_enabled",
            f"equalizer on/off works only while CAN on/off is enabled, and {which}: "
            "add `can_onoff_enable: true` to this command to enable it first",
        )


def parameter_payload(units: list[UnitState], body: Mapping[str, Json]) -> CommandPayload:
    """A parameter write validated against every unit on the bus (each one applies it);
    a reason that holds for some of them only names them."""
    values = {k: v for k, v in body.items() if k not in ("unit", "expires_in_s", "all_units")}
    by_reason: dict[str, list[UnitState]] = {}
    for u in units:
        for reason in validate_parameter_write(values, u.series):
            by_reason.setdefault(reason, []).append(u)
    reasons = [
        reason
        if len(who) == len(units)
        else ", ".join(f"unit {u.ref.sa}" for u in who) + f": {reason}"
        for reason, who in by_reason.items()
    ]
    if reasons:
        kind = "unsupported_field" if all("not supported" in r for r in reasons) else None
        raise CommandRefused(422, kind or "invalid_parameters", "; ".join(reasons), reasons=reasons)
    return {"request": dict(body), "values": values}


def request_payload(body: Mapping[str, Json]) -> CommandPayload:
    what = body.get("what")
    if not isinstance(what, str) or what not in REQUESTS:
        raise CommandRefused(422, "invalid_request", f"cannot request {what!r}")
    pgn, slot = REQUESTS[what]
    return {"request": dict(body), "what": what, "pgn": pgn, "slot": slot}


def targets(cmd: Command) -> set[str]:
    p = cmd.payload
    if cmd.kind == CommandKind.CONTROL:
        return set(p["fields"])
    if cmd.kind == CommandKind.PARAMETERS:
        return set(p["values"])
    return {p["what"]}


def conflict(pending: Command, new: Command) -> set[str]:
    """What two commands of one kind for one unit (or bus) would fight over: the same
    field, or one undoing the other. Disabling CAN on/off takes equalizer on/off out of
    the gateway's hands; a factory reset (or a reset profile) puts every parameter back."""
    a, b = targets(pending), targets(new)
    clash = a & b
    if new.kind == CommandKind.CONTROL:
        for x, y in ((pending, new), (new, pending)):
            if x.payload["fields"].get("can_onoff_en") == "disable" and (
                "can_eq_onoff" in y.payload["fields"]
            ):
                clash |= {"can_onoff_en", "can_eq_onoff"}
    elif new.kind == CommandKind.PARAMETERS and a and b and (a | b) & RESET_PARAMETERS:
        clash |= (a | b) & RESET_PARAMETERS
    return clash
