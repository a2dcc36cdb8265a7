"""Submission checks: what a command reaches, and why it is refused before it is queued."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

from eqgw.commands.model import AffectedUnit, Command, Json
from eqgw.ingest.state import UnitState
from eqgw.protocol.j1939 import (
    PGN_COMPONENT_ID,
    PGN_DM1,
    PGN_SOFTWARE_ID,
)
from eqgw.protocol.params import FACTORY_RESET

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
