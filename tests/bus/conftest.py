"""Fixtures of the bus tests: real virtual buses, and a check that nothing is left running."""

from __future__ import annotations

import asyncio
import threading
import time
import uuid
from collections.abc import AsyncIterator, Iterator

import can
import can.interfaces.virtual
import pytest

from tests.bus_helpers import TIMEOUT


@pytest.fixture(autouse=True)
async def no_leftovers() -> AsyncIterator[None]:
    """Fail a test that leaves a bus, a Notifier, a thread or a task running."""
    threads_before = set(threading.enumerate())
    yield
    current = asyncio.current_task()
    tasks = [t for t in asyncio.all_tasks() if t is not current and not t.done()]
    assert not tasks, f"tasks left running: {tasks}"
    deadline = time.monotonic() + TIMEOUT
    while True:
        extra = [t for t in threading.enumerate() if t not in threads_before and t.is_alive()]
        if not extra or time.monotonic() > deadline:
            break
        await asyncio.sleep(0.02)
    assert not extra, f"threads left running: {extra}"
    assert not can.interfaces.virtual.channels, "virtual buses left open"
    assert not can.Notifier._registry.pairs, "notifiers left running"


@pytest.fixture
def channel() -> str:
    """A virtual channel no other test uses."""
    return f"test-{uuid.uuid4().hex[:8]}"


@pytest.fixture
def sim(channel: str) -> Iterator[can.BusABC]:
    """The other end of the bus: what the simulator or the vehicle would be."""
    bus = can.Bus(interface="virtual", channel=channel)
    yield bus
    bus.shutdown()
