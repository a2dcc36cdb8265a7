"""Ending background tasks within a bound, without losing the caller's own cancellation
(`cancel_and_wait`; `in_thread_until_stopped` for a job in a thread, which a cancel alone
does not end); the one backoff of every retry loop; and `classify`, which tells the faults a
retry may cure from those it never will.

Every retry loop asks `classify(exc)` (or `heals(exc)`) in its `except`:

- `heals`: a connection refused, reset or timed out, a database restarting or locked, a
  full disk, an HTTP 5xx or 429, anything not known to be lasting: retried with `Backoff`
  and reported while it fails.
- `fatal`: storage that will not heal (a damaged or read-only SQLite file, a database or
  role that does not exist, a refused database login, a permission): the process ends with
  one line and a non-zero exit (the supervisor's `on_fatal`).
- lasting, not fatal: a programming error (`TypeError`, `AttributeError`, `KeyError`, ...),
  a refusal of credentials or authorisation by a service the task talks to (an exception
  carrying `heals = False`, e.g. an MQTT broker's "not authorised"): the task stops, says so
  in one line and is reported failed (/readyz, /metrics); retrying would only repeat it.
"""

from __future__ import annotations

import asyncio
import logging
import random
import re
import sqlite3
import threading
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import TypeVar

T = TypeVar("T")

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


async def in_thread_until_stopped(
    job: Callable[[threading.Event], T], *, stop_wait_s: float = STOP_TIMEOUT_S
) -> T:
    """`job(stop)` run in a thread (`asyncio.to_thread`); its result, or its exception.

    A cancel of the caller does not stop a thread: the job is told by `stop` (it looks before
    each transaction or step and ends there), the cancel waits for it, at most `stop_wait_s`
    (a job that does not end by then is logged and left), and the cancel goes on. So a task's
    stop() ends what its thread was doing, and nothing of it runs on an engine disposed of
    after the stop."""
    stop = threading.Event()
    running = asyncio.ensure_future(asyncio.to_thread(job, stop))
    try:
        return await asyncio.shield(running)
    except asyncio.CancelledError:
        stop.set()
        await asyncio.wait({running}, timeout=stop_wait_s)
        if not running.done():
            log.error("a thread's job did not end within %g s of its stop", stop_wait_s)
        elif not running.cancelled():
            running.exception()  # seen: the cancel goes on either way
        raise


# The jitter's own generator: a retry leaves the `random` module's state as it found it (a
# program that seeds it, or checks it, as Hypothesis does while it draws, sees no change).
_JITTER = random.Random()


def backoff_delay(
    attempts: int, initial_s: float, max_s: float, rand: Callable[[], float] = _JITTER.random
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
        rand: Callable[[], float] = _JITTER.random,
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


# -- which faults heal ----------------------------------------------------------------------

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
# Programming errors: the code is wrong, not the world; the same input fails the same way.
# (ValueError and ArithmeticError are left out: bad data from outside raises them too.)
BUG_TYPES: tuple[type[BaseException], ...] = (
    TypeError,
    AttributeError,
    NameError,
    LookupError,
    AssertionError,
    NotImplementedError,
    ImportError,
    RecursionError,
)


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
    """Why `exc` is storage (or a permission) that will never heal by retrying, the process's
    end (a short reason), or None when it may heal."""
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


@dataclass(frozen=True, slots=True)
class Fault:
    """What a retry loop does with a failure: `heals` (retry with backoff), else stop; a
    `fatal` one ends the process. `reason` is short, for the one log line."""

    heals: bool
    fatal: bool
    reason: str
    bug: bool = False


HEALS = Fault(heals=True, fatal=False, reason="may heal")


def classify(exc: BaseException) -> Fault:
    """Whether a retry may cure `exc` (see the module's docstring)."""
    reason = permanent_fault(exc)
    if reason is not None:
        return Fault(heals=False, fatal=True, reason=reason)
    # A bug is the exception raised, or the one SQLAlchemy wraps (a bind parameter's
    # TypeError); not one met while handling another (__context__).
    for e in (exc, getattr(exc, "orig", None)):
        if isinstance(e, BUG_TYPES):
            return Fault(heals=False, fatal=False, reason=f"a bug: {type(e).__name__}", bug=True)
    for e in _chain(exc):
        if getattr(e, "heals", None) is False:
            return Fault(heals=False, fatal=bool(getattr(e, "fatal", False)), reason="refused")
    return HEALS


def heals(exc: BaseException) -> bool:
    """Whether a retry may cure `exc`: `classify(exc).heals`."""
    return classify(exc).heals


def http_status_heals(status: int) -> bool:
    """Whether an HTTP answer's failure may pass: a 5xx, 408 (timeout), 425 and 429 (too
    early, too many) may; any other 4xx (a refused key or signature, a wrong address, a
    body the receiver will never take) is the same at the next try."""
    return status >= 500 or status in (408, 425, 429)


class Refused(Exception):
    """A service refused what this task sends for a reason no retry cures (its credentials,
    its authorisation): `heals` is False; `fatal` when the process cannot work without it."""

    heals = False

    def __init__(self, message: str, *, fatal: bool = False) -> None:
        super().__init__(message)
        self.fatal = fatal
