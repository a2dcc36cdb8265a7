"""What a forwarder and the central service agree on: the frame filter and the upload shape.

An upload is JSON (gzip-compressed on the wire by default):

    {"stream": "<buffer uuid>", "vehicle": "BUS-101", "bus": "BUS-101/can0",
     "equalizer_sas": [30], "first_seq": 1201, "dropped": 0,
     "frames": [[ts, can_id, "data hex", flags], ...]}

`frames` carry consecutive sequence numbers from `first_seq`; `flags` is a bit set
(`FLAG_EXTENDED`, `FLAG_REMOTE`, `FLAG_ERROR`). The answer's `acked_seq` is the highest
sequence number the central service has committed for the stream.
"""

from __future__ import annotations

from collections.abc import Collection
from typing import Any

from eqgw.protocol.j1939 import PGN_CONTROL, PGN_PARAMETERS, PGN_REQUEST

FLAG_EXTENDED = 1
FLAG_REMOTE = 2
FLAG_ERROR = 4
MAX_FRAMES_PER_UPLOAD = 20_000
MAX_DATA_BYTES = 8  # classic CAN: a J1939 frame carries at most 8 data bytes


def flags_of(msg: Any) -> int:
    """The upload flags of a `can.Message`."""
    return (
        (FLAG_EXTENDED if msg.is_extended_id else 0)
        | (FLAG_REMOTE if msg.is_remote_frame else 0)
        | (FLAG_ERROR if msg.is_error_frame else 0)
    )


def is_equalizer_frame(can_id: int, flags: int, equalizer_sas: Collection[int]) -> bool:
    """Whether the ingest keeps anything of this frame: the rule of the raw archive (frames from
    an equalizer, control and parameter frames, requests to an equalizer or to all), on
    29-bit data frames."""
    if flags != FLAG_EXTENDED:
        return False
    if (can_id & 0xFF) in equalizer_sas:
        return True
    pgn = (can_id >> 8) & 0x3FFFF
    if (pgn & 0x3FF00) == PGN_REQUEST:
        da = pgn & 0xFF
        return da in equalizer_sas or da == 0xFF
    return pgn == PGN_CONTROL or pgn == PGN_PARAMETERS


def default_bus_name(vehicle: str, channel: str) -> str:
    """The bus name forwarded frames are filed under: `<vehicle>/<channel>`, the name an
    `eqgw replay --vehicle CHANNEL=VEHICLE` of the same vehicle's log gives, so both dedupe."""
    return f"{vehicle}/{channel}"
