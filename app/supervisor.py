"""Long-running tasks that survive their failures, and the faults that will not heal.

`Supervisor` runs a process's background loops (`eqgw forward`'s reader and uploader, `eqgw
serve`'s maintenance loops): a loop that raises is logged, restarted after a backoff that
doubles up to a bound, and its state, restarts and last error are reported (status lines,
/readyz, /metrics). A failure `permanent_fault` recognises (a corrupt or read-only file, a
database that does not exist) is not retried: the supervisor records it as fatal and calls
its `on_fatal`, and the process ends non-zero with that one line, for systemd or Docker to
restart it or an operator to read.
"""

from __future__ import annotations

import asyncio
import logging
import re
import sqlite3
import time
from collections.abc import Awaitable, Callable, Iterator
from dataclasses import asdict, dataclass
from typing import Any, Literal

from eqgw.describe import describe
from eqgw.tasks import backoff_delay, cancel_and_wait

log = logging.getLogger(__name__)

TaskState = Literal["running", "backoff", "done", "failed"]

# SQLite result codes that no retry cures: the file is not a database or is damaged, it is
# read-only (file mode, mount), it cannot be opened at all, permission or authorisation.
_SQLITE_PERMANENT = {
    3: "SQLITE_PERM",
    8: "SQLITE_READONLY",
    11: "SQLITE_CORRUPT",
    14: "SQLITE_CANTOPEN",
    23: "SQLITE_AUTH",
    26: "SQLITE_NOTADB",
}
# PostgreSQL's answers at connect time that no retry cures (psycopg gives no SQLSTATE there):
# a database or role that does not exist, a refused login.
_PG_PERMANENT = re.compile(
    r'database "[^"]*" does not exist|role "[^"]*" does not exist'
    r"|password authentication failed|no pg_hba\.conf entry|permission denied for database"
)
# SQLSTATE classes and codes that are permanent once a connection exists.
_PG_PERMANENT_STATES = {"3D000", "28000", "28P01", "42501"}


def _chain(exc: BaseException) -> Iterator[BaseException]:
    """The exception, the driver's under SQLAlchemy's (`orig`), and their causes."""
    seen: set[int] = set()
    todo: list[BaseException | None] = [exc]
    while todo:
        e = todo.pop()
        if e is None or id(e) in seen:
            continue
        seen.add(id(e))
        yield e
        todo += [getattr(e, "orig", None), e.__cause__, e.__context__]


def permanent_fault(exc: BaseException) -> str | None:
    """Why `exc` will never heal by retrying (a short reason), or None when it may."""
    for e in _chain(exc):
        if isinstance(e, sqlite3.Error):
            code = getattr(e, "sqlite_errorcode", None)
            if code is not None and (code & 0xFF) in _SQLITE_PERMANENT:
                return _SQLITE_PERMANENT[code & 0xFF]
        state = getattr(e, "sqlstate", None)
        if isinstance(state, str) and state in _PG_PERMANENT_STATES:
            return f"SQLSTATE {state}"
        if type(e).__module__.startswith("psycopg") and _PG_PERMANENT.search(str(e)):
            return "refused by the server"
        if isinstance(e, PermissionError):
            return "permission denied"
    return None


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

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)


class Supervisor:
    """Runs named background loops; restarts a failing one with backoff, ends on a fatal one.

    A loop that returns is done. A loop that raises is restarted after a delay that doubles
    from `backoff[0]` to `backoff[1]` (with jitter), reset once it has run `stable_s` without
    failing. A failure recognised by `permanent_fault` marks the task failed and calls
    `on_fatal(FatalError)` once (the owner stops the process with a non-zero exit).
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

    def start(self, name: str, loop: Callable[[], Awaitable[None]]) -> asyncio.Task[None]:
        """Run `loop()` under supervision as task `name`."""
        if name in self._tasks and not self._tasks[name].done():
            raise ValueError(f"task {name!r} is already running")
        self._status[name] = TaskStatus(name, "running", 0, 0, None, None, time.time())
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
        first, longest = self.backoff
        streak = 0  # failures since the loop last ran for stable_s
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
                reason = permanent_fault(exc)
                if reason is not None:
                    self._set(st, "failed")
                    fatal = FatalError(name, exc)
                    log.error("task %s failed for good (%s): %s", name, reason, st.last_error)
                    if self.fatal is None:
                        self.fatal = fatal
                        if self.on_fatal is not None:
                            self.on_fatal(fatal)
                    return
                if time.monotonic() - started >= self.stable_s:
                    streak = 0
                streak += 1
                delay = backoff_delay(streak, first, longest)
                if st.failures == 1 or st.restarts % 10 == 0:
                    log.warning(
                        "task %s failed (%d so far), restarting in %.1f s: %s",
                        name, st.failures, delay, st.last_error,
                    )  # fmt: skip
                self._set(st, "backoff")
                await asyncio.sleep(delay)
                st.restarts += 1
                continue
            self._set(st, "done")
            return
