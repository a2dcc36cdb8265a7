"""A command as the API shows it: `public_command` is the JSON of `CommandOut`, the schema its
routes publish, field for field and in its order."""

from __future__ import annotations

import pytest

from eqgw.commands.model import Command, CommandKind, CommandPayload, CommandState, public_command
from eqgw.commands.schemas import CommandOut
from eqgw.web.responses import dumps


def _command(payload: CommandPayload, **changes: object) -> Command:
    cmd = Command(
        id="6f1c",
        kind=CommandKind.CONTROL,
        vehicle_id="BUS-101",
        bus="can0",
        sa=0x1E,
        payload=payload,
        state=CommandState.SENDING,
        reason=None,
        created_at=1_763_700_000.25,
        updated_at=1_763_700_001.5,
        expires_at=1_763_700_030.25,
        first_sent_at=1_763_700_000.5,
        last_sent_at=1_763_700_001.5,
        sends=2,
        max_sends=1_000_000,
        handed_at=1_763_700_001.5,
        frames_handed=2,
        key_id=3,
        key_name="operator",
        idempotency_key=None,
    )
    for name, value in changes.items():
        setattr(cmd, name, value)
    return cmd


BROADCAST: CommandPayload = {
    "request": {"eq12": "enable", "all_units": True, "expires_in_s": 20},
    "affected_units": [{"sa": 0x1E, "series": 80}, {"sa": 0x1F, "series": None}],
}
# A row queued before `affected_units` was recorded: the addressed unit alone.
OLDER_ROW: CommandPayload = {"request": {"what": "software_id", "unit": 30}}


@pytest.mark.parametrize(
    "cmd",
    [
        _command(BROADCAST),
        _command(
            OLDER_ROW,
            kind=CommandKind.REQUEST,
            state=CommandState.QUEUED,
            sends=0,
            first_sent_at=None,
            last_sent_at=None,
            key_name=None,
        ),
    ],
    ids=["broadcast", "older-row"],
)
def test_public_command_is_command_out(cmd: Command) -> None:
    out = public_command(cmd)
    assert list(out) == list(CommandOut.model_fields)
    as_schema = CommandOut.model_validate(out).model_dump(mode="json")
    assert dumps(as_schema) == dumps(out)


def test_a_command_reaches_its_own_unit_when_its_row_names_none() -> None:
    assert public_command(_command(OLDER_ROW))["affected_units"] == [{"sa": 0x1E, "series": None}]
