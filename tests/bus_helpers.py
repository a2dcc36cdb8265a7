"""Helpers of the bus tests: waiting on conditions and on virtual endpoints without blocking."""

from __future__ import annotations

import asyncio
import time
from collections.abc import Awaitable, Callable
from typing import TypeVar

import can
import pytest

TIMEOUT = 15.0
T = TypeVar("T")


async def within(aw: Awaitable[T], timeout: float) -> T:
    """`await aw`, failing with TimeoutError after `timeout` s: `asyncio.wait_for` without its
    3.11 flaw (a cancel landing as `aw` finishes is dropped)."""
    async with asyncio.timeout(timeout):
        return await aw


async def wait_for(condition: Callable[[], bool], what: str, timeout: float = TIMEOUT) -> None:
    """Poll until condition() holds; fail with `what` after timeout."""
    deadline = time.monotonic() + timeout
    while not condition():
        if time.monotonic() > deadline:
            pytest.fail(f"timed out waiting for {what}")
        await asyncio.sleep(0.01)


async def recv_virtual(bus: can.BusABC, timeout: float = TIMEOUT) -> can.Message:
    """Receive from a virtual endpoint without blocking the event loop."""
    deadline = time.monotonic() + timeout
    while (msg := bus.recv(0)) is None:
        if time.monotonic() > deadline:
            pytest.fail("no frame arrived on the virtual endpoint")
        await asyncio.sleep(0.005)
    return msg
