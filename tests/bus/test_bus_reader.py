"""BusReader and BusWriter on python-can's virtual interface, in one process."""

from __future__ import annotations

import asyncio
import logging
import time
import uuid

import can
import can.interfaces.virtual
import pytest

from eqgw.bus.config import BusConfig
from eqgw.bus.errors import BusClosedError, BusNotOpenError, BusSendError
from eqgw.bus.log_filters import SOCKETCAND_LOGGER, RepeatSummaryFilter
from eqgw.bus.reader import BusReader
from eqgw.bus.writer import BusWriter
from tests.bus_helpers import TIMEOUT, recv_virtual, wait_for, within


def virtual_config(channel: str, **overrides: object) -> BusConfig:
    values: dict[str, object] = {
        "name": "BUS-101/can0",
        "vehicle_id": "BUS-101",
        "interface": "virtual",
        "channel": channel,
    }
    values.update(overrides)
    if values["interface"] == "no-such-interface":
        # The settings refuse an interface python-can does not know; the reader must still
        # survive one that fails to open (a plugin gone since the check): built unchecked.
        return BusConfig.model_construct(**values)  # type: ignore[arg-type]
    return BusConfig.model_validate(values)


def frame(i: int) -> can.Message:
    return can.Message(arbitration_id=0x18FEF11E, data=i.to_bytes(4, "little") + bytes(4))


async def test_frames_arrive_in_order_with_bus_timestamps_and_bus_name(
    channel: str, sim: can.BusABC
) -> None:
    async with BusReader(virtual_config(channel)) as reader:
        await reader.wait_open(TIMEOUT)
        before = time.time()
        for i in range(200):
            sim.send(frame(i))
        after = time.time()
        got = [await within(reader.get(), TIMEOUT) for _ in range(200)]
        status = reader.status()
    assert [int.from_bytes(m.data[:4], "little") for m in got] == list(range(200))
    # The virtual bus stamps frames when sent; the reader must keep that stamp, not its own.
    assert all(before <= m.timestamp <= after for m in got)
    assert all(m.channel == "BUS-101/can0" and m.is_extended_id for m in got)
    assert status.state == "open"
    assert status.frames_total == 200
    assert status.drops == 0
    assert status.reconnects == 0
    assert status.last_error is None
    assert reader.status().state == "closed"


async def test_stalled_consumer_is_bounded_and_drops_are_counted(
    channel: str, sim: can.BusABC
) -> None:
    async with BusReader(virtual_config(channel), queue_size=50) as reader:
        await reader.wait_open(TIMEOUT)
        for i in range(500):
            sim.send(frame(i))
        await wait_for(lambda: reader.status().frames_total == 500, "all frames read")
        status = reader.status()
        assert status.queued == 50
        assert status.drops == 450
        # The oldest frames were kept; the ones that found the buffer full were dropped.
        kept = await reader.get_batch(1000)
        assert [int.from_bytes(m.data[:4], "little") for m in kept] == list(range(50))
        sim.send(frame(999))
        later = await within(reader.get(), TIMEOUT)
        assert int.from_bytes(later.data[:4], "little") == 999
        assert reader.status().frames_per_s > 0


async def test_async_iteration_ends_when_the_reader_stops(channel: str, sim: can.BusABC) -> None:
    reader = BusReader(virtual_config(channel))
    await reader.start()
    await reader.wait_open(TIMEOUT)
    seen: list[can.Message] = []

    async def consume() -> None:
        async for msg in reader:
            seen.append(msg)

    consumer = asyncio.create_task(consume())
    for i in range(3):
        sim.send(frame(i))
    await wait_for(lambda: len(seen) == 3, "three frames")
    await reader.stop()
    await within(consumer, TIMEOUT)
    with pytest.raises(BusClosedError):
        await reader.get()
    assert await reader.get_batch() == []


async def test_writer_transmits_on_the_shared_bus(channel: str, sim: can.BusABC) -> None:
    async with BusReader(virtual_config(channel, gateway_sa=0xF9)) as reader:
        writer = BusWriter(reader)
        assert writer.gateway_sa == 0xF9
        assert writer.name == "BUS-101/can0"
        await reader.wait_open(TIMEOUT)
        await writer.send(0x18EA1EF9, b"\xc8\xfe\x00")
        received = await recv_virtual(sim)
        assert received.arbitration_id == 0x18EA1EF9
        assert received.is_extended_id
        assert bytes(received.data) == b"\xc8\xfe\x00"
        # What the gateway sends does not come back to its own reader.
        sim.send(frame(7))
        echo = await within(reader.get(), TIMEOUT)
        assert echo.arbitration_id == 0x18FEF11E
        with pytest.raises(ValueError):
            await writer.send(0x2000_0000, b"")
        with pytest.raises(ValueError):
            await writer.send(0x18EA1EF9, bytes(9))


async def test_a_send_with_a_deadline_is_never_handed_over_late(
    channel: str, sim: can.BusABC
) -> None:
    async with BusReader(virtual_config(channel)) as reader:
        writer = BusWriter(reader)
        await reader.wait_open(TIMEOUT)
        bus = reader._bus
        assert bus is not None
        timeouts: list[float | None] = []
        send = bus.send

        def recording(msg: can.Message, timeout: float | None = None) -> None:
            timeouts.append(timeout)  # the virtual bus has no transmit queue to time out on
            send(msg, timeout)

        bus.send = recording  # type: ignore[method-assign]
        # Its deadline passed (e.g. while another command's send held the bus): not sent.
        with pytest.raises(BusSendError, match="deadline"):
            await writer.send(0x18EA1ED8, b"\x01", deadline=time.time() - 0.001)
        assert timeouts == []
        # Otherwise the interface's own send timeout ends at the deadline ...
        await writer.send(0x18EA1ED8, b"\x02", deadline=time.time() + 0.5)
        # ... or is the reader's send timeout without one.
        await writer.send(0x18EA1ED8, b"\x03")
        first, second = timeouts
        assert first is not None and 0 < first <= 0.5 and second == reader.send_timeout
        assert [bytes((await recv_virtual(sim)).data) for _ in range(2)] == [b"\x02", b"\x03"]


def test_default_gateway_source_address_is_0xd8(channel: str) -> None:
    assert BusWriter(BusReader(virtual_config(channel))).gateway_sa == 0xD8


# A SocketCAN device this machine does not have: a bus python-can knows but cannot open.
ABSENT = "eqgw-absent0"


def absent_config() -> BusConfig:
    return BusConfig(name="absent", vehicle_id="V", interface="socketcan", channel=ABSENT)


async def test_writer_refuses_when_the_bus_is_not_open(channel: str) -> None:
    idle = BusWriter(BusReader(virtual_config(channel)))
    with pytest.raises(BusNotOpenError, match="closed"):
        await idle.send(0x18EA1ED8, b"\x00")
    broken = BusReader(absent_config(), backoff=(0.05, 0.1))
    async with broken:
        await wait_for(lambda: broken.status().last_error is not None, "an open failure")
        with pytest.raises(BusNotOpenError, match=ABSENT):
            await BusWriter(broken).send(0x18EA1ED8, b"\x00")


async def test_open_failures_back_off_and_are_reported_without_crashing(
    channel: str, caplog: pytest.LogCaptureFixture
) -> None:
    reader = BusReader(absent_config(), backoff=(0.05, 0.2))
    seen_states: set[str] = set()
    async with reader:

        def failed_twice() -> bool:
            seen_states.add(reader.status().state)
            return reader.status().last_error_at is not None and "backoff" in seen_states

        await wait_for(failed_twice, "the reader backing off")
        status = reader.status()
        assert status.state in ("backoff", "connecting")
        assert status.last_error is not None
        assert status.last_error.startswith("open failed:")
        assert ABSENT in status.last_error
        assert status.opened_at is None
    assert reader.status().state == "closed"
    # The same failure again is logged once, not on every retry.
    warnings = [r for r in caplog.records if r.levelno >= logging.WARNING]
    assert len(warnings) == 1


async def test_a_bus_that_fails_while_open_is_reopened(channel: str, sim: can.BusABC) -> None:
    async with BusReader(virtual_config(channel), backoff=(0.05, 0.2)) as reader:
        await reader.wait_open(TIMEOUT)
        sim.send(frame(1))
        await within(reader.get(), TIMEOUT)
        # What an unplugged adapter looks like to python-can: recv() starts raising.
        bus = reader.bus
        assert bus is not None
        bus.shutdown()
        await wait_for(lambda: reader.status().reconnects == 1, "a reconnect")
        await reader.wait_open(TIMEOUT)
        status = reader.status()
        assert status.last_error is not None
        assert "receive failed" in status.last_error
        sim.send(frame(2))
        msg = await within(reader.get(), TIMEOUT)
        assert int.from_bytes(msg.data[:4], "little") == 2


async def test_stop_is_idempotent_and_start_only_once(channel: str) -> None:
    reader = BusReader(virtual_config(channel))
    await reader.start()
    with pytest.raises(RuntimeError):
        await reader.start()
    await reader.stop()
    await reader.stop()
    with pytest.raises(RuntimeError):
        await reader.start()


def test_bad_arguments_are_refused(channel: str) -> None:
    with pytest.raises(ValueError):
        BusReader(virtual_config(channel), backoff=(2.0, 1.0))
    with pytest.raises(ValueError):
        BusReader(virtual_config(channel), queue_size=0)


def test_summary_filter_passes_one_record_per_interval_and_counts_the_rest() -> None:
    summary = RepeatSummaryFilter(["Got incomplete message"], interval=3600)
    logger = logging.getLogger(f"{SOCKETCAND_LOGGER}.test-{uuid.uuid4().hex[:6]}")
    records: list[logging.LogRecord] = []

    class Collect(logging.Handler):
        def emit(self, record: logging.LogRecord) -> None:
            records.append(record)

    handler = Collect()
    logger.addHandler(handler)
    logger.addFilter(summary)
    logger.propagate = False
    try:
        for _ in range(100):
            logger.warning("Got incomplete message => waiting for more data")
        logger.warning("Failed to receive: something else")
    finally:
        logger.removeHandler(handler)
    assert [r.getMessage() for r in records] == [
        "Got incomplete message => waiting for more data",
        "Failed to receive: something else",
    ]
    assert summary.counts() == {"Got incomplete message": 100}


def test_summary_filter_reports_how_many_it_held_back() -> None:
    summary = RepeatSummaryFilter(["noisy"], interval=0.0)
    first = logging.LogRecord("x", logging.WARNING, __file__, 1, "noisy %d", (1,), None)
    second = logging.LogRecord("x", logging.WARNING, __file__, 1, "noisy %d", (2,), None)
    assert summary.filter(first)
    assert summary.filter(second)
    assert first.getMessage() == "noisy 1"
    assert second.getMessage().startswith("noisy 2 (and 0 more like it")
