"""A command as it travels from the API to the store and back: its kind, its state, its row.

`Command` is one row of the `commands` table, typed; `CommandPayload` is the JSON it carries
(what the client asked, what goes on the bus, what confirms it, which units it reaches).
The stored JSON keeps the shape older gateways on the same database read and write.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from enum import StrEnum
from typing import TYPE_CHECKING, TypedDict

from eqgw.jsontypes import JSONObject, JSONValue
from eqgw.protocol.j1939 import PGN_CONTROL, PGN_PARAMETERS

if TYPE_CHECKING:
    from sqlalchemy import RowMapping

# A JSON value as the client sent it (the `request` echoed back and audited).
Json = JSONValue


class CommandKind(StrEnum):
    """What a command writes: control flags (PGN 65490), parameters (65491), or a request
    (PGN 59904) for something a unit answers."""

    CONTROL = "control"
    PARAMETERS = "parameters"
    REQUEST = "request"


class CommandState(StrEnum):
    """Where a command is in its life (docs/commands.md, "End states")."""

    QUEUED = "queued"
    SENDING = "sending"
    CONFIRMED = "confirmed"
    SENT = "sent"
    UNCONFIRMED = "unconfirmed"
    REFUSED = "refused"
    FAILED = "failed"
    EXPIRED = "expired"
    CANCELLED = "cancelled"


_KINDS = {k.value: k for k in CommandKind}
_STATES = {s.value: s for s in CommandState}

# Commands in these states may still reach the bus.
PENDING_STATES = (CommandState.QUEUED, CommandState.SENDING)
# `unconfirmed`: frames were handed to the interface but nothing confirmed them; they may
# still take effect (a link that stalled delivers them when it resumes). `failed` and
# `expired` are for commands of which no frame ever left the gateway. `refused`: a unit
# answered with a J1939 NACK or "access denied" (Acknowledgement PGN 59392).
FINAL_STATES = (
    CommandState.CONFIRMED,
    CommandState.SENT,
    CommandState.UNCONFIRMED,
    CommandState.REFUSED,
    CommandState.FAILED,
    CommandState.EXPIRED,
    CommandState.CANCELLED,
)


class AffectedUnit(TypedDict):
    """A unit a command reaches: its SA and series (None: not learned yet)."""

    sa: int
    series: int | None


class CommandPayload(TypedDict, total=False):
    """The JSON a command row carries. Every kind: `request` (the client's body) and
    `affected_units` (absent on rows queued before it was recorded). Control: `fields` (signal
    -> enable/disable) and `expect` (status flag -> active/inactive). Parameters: `values`
    (name -> value). Request: `what`, the requested `pgn` and the live `slot` of the answer."""

    request: dict[str, Json]
    affected_units: list[AffectedUnit]
    fields: dict[str, str]
    expect: dict[str, str]
    values: dict[str, Json]
    what: str
    pgn: int
    slot: str


class CommandChanges(TypedDict, total=False):
    """Columns of a command row that change during its life."""

    state: str
    reason: str | None
    updated_at: float
    first_sent_at: float | None
    last_sent_at: float | None
    sends: int
    handed_at: float | None
    frames_handed: int


@dataclass(slots=True)
class Command:
    """One command, as queued in the `commands` table."""

    id: str
    kind: CommandKind
    vehicle_id: str
    bus: str
    sa: int
    payload: CommandPayload
    state: CommandState
    reason: str | None
    created_at: float
    updated_at: float
    expires_at: float
    first_sent_at: float | None
    last_sent_at: float | None
    sends: int
    max_sends: int
    handed_at: float | None
    frames_handed: int
    key_id: int | None
    key_name: str | None
    idempotency_key: str | None

    @classmethod
    def from_row(cls, row: RowMapping) -> Command:
        """A command from a row of the `commands` table (a SQLAlchemy row mapping). Spelled
        out: the conflict check reads every pending row of a bus under the bus's lock."""
        r = row
        return cls(
            id=r["id"],
            kind=_KINDS[r["kind"]],
            vehicle_id=r["vehicle_id"],
            bus=r["bus"],
            sa=r["sa"],
            payload=r["payload"],
            state=_STATES[r["state"]],
            reason=r["reason"],
            created_at=r["created_at"],
            updated_at=r["updated_at"],
            expires_at=r["expires_at"],
            first_sent_at=r["first_sent_at"],
            last_sent_at=r["last_sent_at"],
            sends=r["sends"],
            max_sends=r["max_sends"],
            handed_at=r.get("handed_at"),
            frames_handed=r.get("frames_handed", 0),
            key_id=r["key_id"],
            key_name=r["key_name"],
            idempotency_key=r["idempotency_key"],
        )

    def to_row(self) -> dict[str, object]:
        """The columns to insert (states and kinds as their strings)."""
        row: dict[str, object] = {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}
        row["kind"], row["state"] = self.kind.value, self.state.value
        return row

    def apply(self, changes: CommandChanges) -> None:
        """Take the changes written to the row."""
        for name, value in changes.items():
            setattr(self, name, value)
        self.state = CommandState(self.state)

    def refresh(self, other: Command) -> None:
        """Take every column of `other`, the same command read again."""
        for f in dataclasses.fields(self):
            setattr(self, f.name, getattr(other, f.name))

    @property
    def ended(self) -> bool:
        return self.state in FINAL_STATES

    def units(self) -> list[int]:
        """The SAs of the units the command reaches (commands queued before this was
        recorded: the one unit they name)."""
        units = self.payload.get("affected_units")
        return [u["sa"] for u in units] if units else [self.sa]


def command_units(cmd: Command) -> list[int]:
    """The SAs of the units a command reaches (commands queued before this was recorded:
    the one unit they name)."""
    return cmd.units()


def command_pgn(cmd: Command) -> int:
    """The PGN a unit's acknowledgement of this command names: the control or parameter PGN,
    or for a request the PGN requested."""
    if cmd.kind == CommandKind.CONTROL:
        return PGN_CONTROL
    if cmd.kind == CommandKind.PARAMETERS:
        return PGN_PARAMETERS
    return cmd.payload["pgn"]


def command_target(cmd: Command) -> str:
    """`bus/SA,SA,...`: where a command goes, for the audit log."""
    return f"{cmd.bus}/{','.join(str(sa) for sa in command_units(cmd))}"


def _reach(cmd: Command) -> list[AffectedUnit]:
    return cmd.payload.get("affected_units") or [{"sa": cmd.sa, "series": None}]


def describe_reach(cmd: Command) -> str:
    """One line for the audit log: the bus and every unit the command reaches."""
    units = _reach(cmd)
    listed = ", ".join(
        f"{u['sa']} ({u['series']}-series)" if u["series"] else f"{u['sa']} (series unknown)"
        for u in units
    )
    return f"reaches bus {cmd.bus}, unit{'s' if len(units) > 1 else ''} {listed}"


def public_command(cmd: Command) -> JSONObject:
    """A command as the API shows it: the fields of `eqgw.commands.schemas.CommandOut`, in its
    order (its routes send this JSON, which the schema documents)."""
    p = cmd.payload
    return {
        "id": cmd.id,
        "kind": cmd.kind.value,
        "vehicle_id": cmd.vehicle_id,
        "bus": cmd.bus,
        "unit": cmd.sa,
        "affected_units": [{"sa": u["sa"], "series": u["series"]} for u in _reach(cmd)],
        "request": p.get("request"),
        "state": cmd.state.value,
        "reason": cmd.reason,
        "created_at": cmd.created_at,
        "updated_at": cmd.updated_at,
        "expires_at": cmd.expires_at,
        "first_sent_at": cmd.first_sent_at,
        "last_sent_at": cmd.last_sent_at,
        "sends": cmd.sends,
        "key_name": cmd.key_name,
    }
