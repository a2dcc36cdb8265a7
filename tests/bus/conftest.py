"""Fixtures of the bus tests: real virtual buses (tests/conftest.py checks nothing is left
running after each test)."""

from __future__ import annotations

import uuid
from collections.abc import Iterator

import can
import can.interfaces.virtual
import pytest


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
