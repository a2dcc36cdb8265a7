"""A cancel that lands as a send finishes is never lost.

On Python 3.11 `asyncio.wait_for` returns the result of an awaited call that finished in the same
loop iteration as a cancel, and the cancel is gone: the command delivery task then never ended
and `CommandService.stop()` waited forever (`eqgw serve` ignoring SIGTERM, a test suite hanging).
"""

from __future__ import annotations

import asyncio
import threading
import time

import can

from eqgw.bus.config import BusConfig
from eqgw.bus.reader import BusReader
from tests.bus_helpers import TIMEOUT


def _send_threads(name: str) -> list[threading.Thread]:
    return [t for t in threading.enumerate() if t.name == f"eqgw bus {name}: send"]


async def test_a_cancel_that_lands_as_the_send_finishes_ends_the_sender(channel: str) -> None:
    config = BusConfig(name="BUS-101/can0", vehicle_id="BUS-101", interface="virtual",
                       channel=channel)  # fmt: skip
    async with BusReader(config) as reader:
        await reader.wait_open(TIMEOUT)
        bus = reader.bus
        assert bus is not None
        # Instrumentation only: hold the driver's send until the test lets it go, so the
        # cancel can be placed exactly where it used to be lost.
        go = threading.Event()
        real_send = bus.send

        def held_send(msg: can.Message, timeout: float | None = None) -> None:
            go.wait(TIMEOUT)
            real_send(msg, timeout=timeout)

        bus.send = held_send  # type: ignore[method-assign]
        msg = can.Message(arbitration_id=0x18FFD2D8, data=bytes(8))
        sender = asyncio.create_task(reader.send_message(msg))
        await asyncio.sleep(0.05)
        assert _send_threads(reader.name), "the send is under way in its thread"
        # Let the send finish and its thread queue the result on the loop, then cancel before
        # the loop runs anything: the result and the cancel arrive in one loop iteration.
        go.set()
        deadline = time.monotonic() + TIMEOUT
        while any(t.is_alive() for t in _send_threads(reader.name)):
            assert time.monotonic() < deadline, "the send thread did not end"
            time.sleep(0.001)  # blocking the loop on purpose
        sender.cancel()
        done, _ = await asyncio.wait({sender}, timeout=TIMEOUT)
        assert done, "the sender did not end"
        assert sender.cancelled(), "the cancel was dropped: the sender returned normally"
