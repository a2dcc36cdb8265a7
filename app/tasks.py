"""Ending background tasks within a bound, without losing the caller's own cancellation."""

from __future__ import annotations

import asyncio
import logging
import random
from collections.abc import Callable

log = logging.getLogger(__name__)

# How long a stop() waits for a cancelled task before it leaves it behind (logged).
STOP_TIMEOUT_S = 5.0


async def cancel_and_wait(
    task: asyncio.Task[object], timeout: float = STOP_TIMEOUT_S, *, quiet: bool = False
) -> bool:
    """Cancel `task` and wait for it to end, at most `timeout` seconds; False if it did not.

    Not `with suppress(CancelledError): await task`, which would also swallow a cancel of the
    caller, nor `asyncio.wait_for`, which on 3.11 can drop a cancel: a task that still runs after
    the bound is logged and left, so no stop() waits forever. A task that had failed is logged
    too, unless `quiet` (its failure is expected, e.g. a client that went away)."""
    task.cancel()
    done, _ = await asyncio.wait({task}, timeout=timeout)
    if not done:
        log.error("task %r did not end within %g s of its cancel", task.get_name(), timeout)
        return False
    if not quiet and not task.cancelled() and task.exception() is not None:
        log.error("task %r had failed", task.get_name(), exc_info=task.exception())
    return True


def backoff_delay(
    attempts: int, initial_s: float, max_s: float, rand: Callable[[], float] = random.random
) -> float:
    """Seconds before the next try after `attempts` failures: doubling from `initial_s` up to
    `max_s`, with "equal jitter" (half fixed, half random) so that many deliveries failing
    together do not retry in step."""
    delay = min(max_s, initial_s * 2.0 ** min(attempts - 1, 60))
    return delay / 2 + rand() * delay / 2


class Backoff:
    """The delays of one retry loop: `backoff_delay`'s doubling from `initial_s` up to `max_s`
    with equal jitter (`jitter=False`: the plain doubling, for a loop that is alone in
    retrying). `next()` after a failure, `reset()` after a success; `delay` is the nominal
    delay of the next failure (for log lines that say what comes)."""

    def __init__(
        self,
        initial_s: float,
        max_s: float,
        *,
        jitter: bool = True,
        rand: Callable[[], float] = random.random,
    ) -> None:
        self.initial_s, self.max_s, self.jitter, self._rand = initial_s, max_s, jitter, rand
        self.failures = 0

    @property
    def delay(self) -> float:
        return min(self.max_s, self.initial_s * 2.0 ** min(self.failures, 60))

    def next(self) -> float:
        self.failures += 1
        if self.jitter:
            return backoff_delay(self.failures, self.initial_s, self.max_s, self._rand)
        return min(self.max_s, self.initial_s * 2.0 ** min(self.failures - 1, 60))

    def reset(self) -> None:
        self.failures = 0
