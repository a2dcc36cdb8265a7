"""Simulated time: a clock tests step by hand and a real-time clock that can run faster."""

from __future__ import annotations

import math
import time
from typing import Protocol


class SimClock(Protocol):
    """Source of simulated time in seconds (epoch-like: used as frame timestamps)."""

    def now(self) -> float: ...

    @property
    def stepped(self) -> bool:
        """True when time moves only when the owner steps it (no background ticker)."""
        ...


class ManualClock:
    """A clock that moves only when told: deterministic tests step it with `advance()`."""

    def __init__(self, start: float = 0.0) -> None:
        self._now = float(start)

    def now(self) -> float:
        return self._now

    @property
    def stepped(self) -> bool:
        return True

    def advance(self, seconds: float) -> float:
        """Move time forward by `seconds` and return the new time."""
        if seconds < 0:
            raise ValueError("time does not run backwards")
        self._now += seconds
        return self._now

    def set(self, when: float) -> None:
        """Move time forward to `when` (never backwards)."""
        if when < self._now:
            raise ValueError("time does not run backwards")
        self._now = when


class RealtimeClock:
    """Wall-clock time, optionally `speed` times faster, starting at `epoch` (default: now)."""

    def __init__(self, speed: float = 1.0, epoch: float | None = None) -> None:
        if speed <= 0:
            raise ValueError("speed must be positive")
        self.speed = speed
        self.epoch = time.time() if epoch is None else epoch
        self._mono0 = time.monotonic()

    def now(self) -> float:
        return self.epoch + (time.monotonic() - self._mono0) * self.speed

    @property
    def stepped(self) -> bool:
        return False


def next_after(scheduled: float, now: float, period: float) -> float:
    """The first time of a periodic schedule (`scheduled` + k * `period`) later than `now`."""
    if scheduled > now:
        return scheduled
    return scheduled + (math.floor((now - scheduled) / period + 1e-9) + 1) * period
