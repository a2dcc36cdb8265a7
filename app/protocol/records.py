"""The decoded record: one equalizer message, in the shape of SPEC-NOTES."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any


@dataclass(slots=True)
class Record:
    """One decoded message: `{"ts", "channel", "sa", "pgn", "name", "fields"}`."""

    ts: float
    channel: str | None
    sa: int
    pgn: int
    name: str
    fields: dict[str, Any] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        return {
            "ts": self.ts,
            "channel": self.channel,
            "sa": self.sa,
            "pgn": self.pgn,
            "name": self.name,
            "fields": self.fields,
        }
