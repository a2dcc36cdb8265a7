"""Long-running tasks that survive their failures, and the faults that will not heal.

`Supervisor` runs a process's background loops (`eqgw forward`'s reader and uploader, `eqgw
serve`'s maintenance loops): a loop that raises is logged, restarted after a backoff that
doubles up to a bound (`tasks.Backoff`), and its state, restarts and last error are reported
(status lines, /readyz, /metrics). What a failure is, `tasks.classify` says:

- one that heals (a connection refused, a database restarting): restarted after the backoff;
- a fatal one (a corrupt or read-only file, a database that does not exist): not retried; the
  supervisor records it as fatal and calls its `on_fatal`, and the process ends non-zero with
  that one line, for systemd or Docker to restart it or an operator to read;
- any other lasting one (a bug, a refused credential): not retried; the task is `failed`,
  said in one line (a bug with its traceback) and reported, the process goes on.
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import AsyncIterator, Awaitable, Callable
from contextlib import asynccontextmanager
from dataclasses import asdict, dataclass
from typing import Any, Literal

from eqgw.describe import describe
from eqgw.tasks import Backoff, Fault, cancel_and_wait, classify, permanent_fault

log = logging.getLogger(__name__)

TaskState = Literal["running", "backoff", "done", "failed"]

__all__ = ["FatalError", "Supervisor", "TaskStatus", "permanent_fault", "spawn"]


class FatalError(Exception):
    """A supervised task met a fault that will not heal; the process should end."""

    def __init__(self, task: str, exc: BaseException) -> None:
        super().__init__(f"{task}: {describe(exc)}")
        self.task = task


@dataclass(slots=True)
class TaskStatus:
    """One supervised task's health."""

    name: str
    state: TaskState
    restarts: int  # times it was started again after a failure
    failures: int
    last_error: str | None
    last_error_at: float | None
    since: float  # when it entered its state (wall clock)
    # Whether its failing for good makes the process not ready (/readyz); a task that only
    # reports (alert delivery, telemetry) is `critical=False`.
    critical: bool = True

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)


class Supervisor:
    """Runs named background loops; restarts a failing one with backoff, ends on a fatal one.

    A loop that returns is done. A loop that raises a fault that heals is restarted after a
    delay that doubles from `backoff[0]` to `backoff[1]` (with jitter), reset once it has run
    `stable_s` without failing. A fault that will not heal (`tasks.classify`) marks the task
    failed, said once; a fatal one also calls `on_fatal(FatalError)` once (the owner stops
    the process with a non-zero exit).
    """

    def __init__(
        self,
        *,
        backoff: tuple[float, float] = (0.5, 30.0),
        stable_s: float = 30.0,
        on_fatal: Callable[[FatalError], None] | None = None,
    ) -> None:
        if not 0 < backoff[0] <= backoff[1]:
            raise ValueError("backoff is (first delay, longest delay), 0 < first <= longest")
        self.backoff = backoff
        self.stable_s = stable_s
        self.on_fatal = on_fatal
        self.fatal: FatalError | None = None
        self._status: dict[str, TaskStatus] = {}
        self._tasks: dict[str, asyncio.Task[None]] = {}

    def start(
        self, name: str, loop: Callable[[], Awaitable[None]], *, critical: bool = True
    ) -> asyncio.Task[None]:
        """Run `loop()` under supervision as task `name`."""
        if name in self._tasks and not self._tasks[name].done():
            raise ValueError(f"task {name!r} is already running")
        self._status[name] = TaskStatus(
            name, "running", 0, 0, None, None, time.time(), critical=critical
        )
        task = asyncio.create_task(self._run(name, loop), name=name)
        self._tasks[name] = task
        return task

    def status(self) -> list[TaskStatus]:
        return list(self._status.values())

    def get(self, name: str) -> TaskStatus | None:
        return self._status.get(name)

    @property
    def healthy(self) -> bool:
        """No task is failed or backing off."""
        return all(s.state in ("running", "done") for s in self._status.values())

    async def __aenter__(self) -> Supervisor:
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.stop()

    @asynccontextmanager
    async def running(
        self, name: str, loop: Callable[[], Awaitable[None]], *, critical: bool = True
    ) -> AsyncIterator[asyncio.Task[None]]:
        """`loop()` supervised as task `name` for the block; cancelled (bounded) at its end."""
        task = self.start(name, loop, critical=critical)
        try:
            yield task
        finally:
            await cancel_and_wait(task)

    async def stop(self, timeout: float = 10.0) -> None:
        """Cancel every task and wait for them, at most `timeout` seconds in all."""
        tasks = [t for t in self._tasks.values() if not t.done()]
        await asyncio.gather(*(cancel_and_wait(t, timeout) for t in tasks))
        self._tasks.clear()

    def _set(self, st: TaskStatus, state: TaskState) -> None:
        if st.state != state:
            st.state = state
            st.since = time.time()

    async def _run(self, name: str, loop: Callable[[], Awaitable[None]]) -> None:
        st = self._status[name]
        backoff = Backoff(*self.backoff)
        while True:
            started = time.monotonic()
            self._set(st, "running")
            try:
                await loop()
            except asyncio.CancelledError:
                raise
            except Exception as exc:
                st.failures += 1
                st.last_error = describe(exc)
                st.last_error_at = time.time()
                fault = classify(exc)
                if not fault.heals:
                    self._fail(st, exc, fault)
                    return
                if time.monotonic() - started >= self.stable_s:
                    backoff.reset()
                delay = backoff.next()
                if st.failures == 1 or st.restarts % 10 == 0:
                    log.warning(
                        "task %s failed (%d so far), restarting in %.1f s: %s",
                        name,
                        st.failures,
                        delay,
                        st.last_error,
                    )
                self._set(st, "backoff")
                await asyncio.sleep(delay)
                st.restarts += 1
                continue
            self._set(st, "done")
            return

    def _fail(self, st: TaskStatus, exc: Exception, fault: Fault) -> None:
        """A failure no retry cures: said once, the task `failed`; a fatal one ends the
        process (`on_fatal`, once)."""
        self._set(st, "failed")
        if not fault.fatal:
            # A bug gets its traceback: the one line alone would not say where it is.
            log.error(
                "task %s stopped, not retried (%s): %s",
                st.name,
                fault.reason,
                st.last_error,
                exc_info=exc if fault.bug else None,
            )
            return
        log.error("task %s failed for good (%s): %s", st.name, fault.reason, st.last_error)
        if self.fatal is None:
            self.fatal = FatalError(st.name, exc)
            if self.on_fatal is not None:
                self.on_fatal(self.fatal)


def spawn(
    supervisor: Supervisor | None,
    name: str,
    loop: Callable[[], Awaitable[None]],
    *,
    critical: bool = True,
) -> asyncio.Task[None]:
    """`loop()` as task `name`: under `supervisor` when there is one (the gateway's), else a
    plain task whose owner's stop() collects it (a component run on its own, in tests)."""
    if supervisor is not None:
        return supervisor.start(name, loop, critical=critical)

    async def run() -> None:
        await loop()

    return asyncio.create_task(run(), name=name)
