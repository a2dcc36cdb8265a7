"""`eqgw.tasks.in_thread_until_stopped`: a job in a thread that a cancel of its caller ends.
A cancel alone would leave the thread running (asyncio cannot stop one); the job is told to
stop, the cancel waits for it within a bound, and the cancel goes on."""

from __future__ import annotations

import asyncio
import logging
import threading
import time

import pytest

from eqgw.tasks import in_thread_until_stopped


async def test_the_result_and_the_exception_of_a_job_reach_the_caller() -> None:
    assert await in_thread_until_stopped(lambda stop: 6 * 7) == 42

    def fails(stop: threading.Event) -> int:
        raise ValueError("a job's own fault")

    with pytest.raises(ValueError, match="a job's own fault"):
        await in_thread_until_stopped(fails)


async def test_a_cancel_tells_the_job_and_waits_for_its_end() -> None:
    started = threading.Event()
    steps_after_stop: list[int] = []
    ended = threading.Event()

    def job(stop: threading.Event) -> int:
        started.set()
        n = 0
        while not stop.is_set():
            n += 1
            time.sleep(0.01)
        steps_after_stop.append(n)
        time.sleep(0.2)  # the step it was in, finished after the stop
        ended.set()
        return n

    task = asyncio.ensure_future(in_thread_until_stopped(job))
    await asyncio.to_thread(started.wait, 30)
    task.cancel()
    with pytest.raises(asyncio.CancelledError):
        await task
    # The cancel returned only once the job had ended: nothing of it runs on.
    assert ended.is_set() and len(steps_after_stop) == 1


async def test_a_job_that_does_not_stop_is_left_after_the_bound_and_said(
    caplog: pytest.LogCaptureFixture,
) -> None:
    started = threading.Event()
    release = threading.Event()

    def deaf(stop: threading.Event) -> None:
        started.set()
        release.wait(30)  # does not look at `stop`

    task = asyncio.ensure_future(in_thread_until_stopped(deaf, stop_wait_s=0.2))
    await asyncio.to_thread(started.wait, 30)
    t0 = time.monotonic()
    with caplog.at_level(logging.ERROR, logger="eqgw.tasks"):
        task.cancel()
        with pytest.raises(asyncio.CancelledError):
            await task
    assert time.monotonic() - t0 < 10  # bounded, not the job's 30 s
    assert "did not end within 0.2 s of its stop" in caplog.text
    release.set()  # the thread ends (the leftovers check sees no thread of this test)
    await asyncio.sleep(0.1)
