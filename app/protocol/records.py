"""The decoded record: one equalizer message, in the shape of SPEC-NOTES."""

from __future__ import annotations

from dataclasses import dataclass, field

from eqgw.jsontypes import JSONObject


@dataclass(slots=True)
class Record:
    """One decoded message: `{"ts", "channel", "sa", "pgn", "name", "fields"}`."""

    ts: float
    channel: str | None
    sa: int
    pgn: int
    name: str
    fields: JSONObject = field(default_factory=dict)

    def to_dict(self) -> JSONObject:
        return {
            "ts": self.ts,
            "channel": self.channel,
            "sa": self.sa,
            "pgn": self.pgn,
            "name": self.name,
            "fields": self.fields,
        }
