"""The transmit path of one bus: frames from the gateway go out through its reader's bus."""

from __future__ import annotations

import can

from eqgw.bus.reader import BusReader

MAX_EXTENDED_ID = 0x1FFFFFFF


class BusWriter:
    """Sends frames on the bus a BusReader keeps open (one python-can Bus per bus, shared)."""

    def __init__(self, reader: BusReader) -> None:
        self.reader = reader

    @property
    def name(self) -> str:
        """The bus this writer transmits on."""
        return self.reader.name

    @property
    def gateway_sa(self) -> int:
        """The gateway's J1939 source address on this bus, for composing identifiers."""
        return self.reader.gateway_sa

    def may_transmit(self) -> bool:
        """Whether a frame sent now would go out: the bus is open and, with address claiming
        on, the gateway holds its address (a lost claim stops every transmission)."""
        return self.reader.may_transmit()

    async def send(
        self,
        can_id: int,
        data: bytes,
        *,
        is_extended_id: bool = True,
        deadline: float | None = None,
    ) -> None:
        """Transmit one frame; BusNotOpenError unless the bus is open, BusSendError on failure.

        `deadline` (epoch s): the frame is not handed to the interface once it has passed
        (waiting for the bus's other sends included), and the interface's own send timeout
        ends there, so a driver whose transmit queue is full gives up instead of sending late.
        """
        limit = MAX_EXTENDED_ID if is_extended_id else 0x7FF
        if not 0 <= can_id <= limit:
            raise ValueError(f"CAN identifier 0x{can_id:X} is out of range (max 0x{limit:X})")
        if len(data) > 8:
            raise ValueError(f"classic CAN carries at most 8 data bytes, got {len(data)}")
        msg = can.Message(
            arbitration_id=can_id, data=bytes(data), is_extended_id=is_extended_id, is_rx=False
        )
        await self.reader.send_message(msg, deadline=deadline)
