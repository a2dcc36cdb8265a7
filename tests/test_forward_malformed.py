"""The forwarder never buffers a frame longer than a J1939 frame: the central service refuses
an upload holding one (more than 8 data bytes), which would stall the stream for good."""

from __future__ import annotations

import uuid
from pathlib import Path

import can

from eqgw.bus.config import BusConfig
from eqgw.forward.buffer import FrameBuffer
from eqgw.forward.uploader import Forwarder, UploadSettings
from tests.forward_helpers import async_wait
from tests.proc_helpers import free_port


async def test_frames_longer_than_8_bytes_are_counted_not_buffered(tmp_path: Path) -> None:
    channel = f"fwd-{uuid.uuid4().hex[:8]}"
    bus = BusConfig(
        name="V/can0", vehicle_id="V", interface="virtual", channel=channel, bitrate=None
    )
    upload = UploadSettings(
        url=f"http://127.0.0.1:{free_port()}/api/v1",  # nothing listens: frames stay buffered
        key="k",
        vehicle="V",
        bus="V",
        backoff_initial_s=0.05,
        backoff_max_s=0.1,
    )
    buffer = FrameBuffer(tmp_path / "fwd.db")
    fwd = Forwarder(bus, buffer, upload)
    truck = can.Bus(interface="virtual", channel=channel)
    try:
        await fwd.start()
        await fwd.reader.wait_open(10)
        voltages = bytes.fromhex("D809B013BA7CC87D")
        truck.send(can.Message(arbitration_id=0x18FFD61E, data=voltages, is_extended_id=True))
        truck.send(
            can.Message(arbitration_id=0x18FFD61E, data=bytes(64), is_extended_id=True, is_fd=True)
        )
        await async_wait(lambda: fwd.frames_read == 2, 10, "both frames read")
        assert (fwd.frames_kept, fwd.frames_malformed) == (1, 1)
        assert fwd.status()["frames_malformed"] == 1
        rows = buffer.peek(10)
        assert len(rows) == 1
        assert (rows[0][2], bytes(rows[0][3])) == (0x18FFD61E, voltages)
    finally:
        await fwd.stop()
        truck.shutdown()
        buffer.close()
