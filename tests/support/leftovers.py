"""What a test leaves running: threads, child processes, listening sockets, virtual buses,
python-can Notifiers and asyncio tasks. The autouse fixture in `tests/conftest.py` takes a
snapshot before each test and fails the test when something it started outlives it."""

from __future__ import annotations

import asyncio
import os
import socket
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import can
import can.interfaces.virtual

from tests.support import forked

# How long what a test stopped may take to be gone (a thread joining, a child reaped, a
# socket closed): generous, since the cores are shared; a clean test does not wait at all.
GRACE_S = 15.0
# A task asked to cancel ends within a few turns of the loop; one never asked runs forever.
TASK_GRACE_S = 2.0


def child_processes() -> frozenset[tuple[int, str]]:
    """Living children of this process, as (pid, start time) so a reused pid is another."""
    found: set[tuple[int, str]] = set()
    try:
        tids = os.listdir("/proc/self/task")
    except OSError:  # no /proc: not checked
        return frozenset()
    pids: set[int] = set()
    for tid in tids:
        try:
            pids.update(int(p) for p in Path(f"/proc/self/task/{tid}/children").read_text().split())
        except OSError:
            continue
    # The fork server of `eqgw` commands (tests/support/forked.py) and its companion outlive
    # the tests; its children are this process's commands.
    helpers = forked.helper_pids()
    pids -= helpers
    if (server := forked.server_pid()) in helpers:
        try:
            forked_children = Path(f"/proc/{server}/task/{server}/children").read_text()
            pids.update(int(p) for p in forked_children.split())
        except OSError:
            pass
    for pid in pids:
        try:
            stat = Path(f"/proc/{pid}/stat").read_text()
        except OSError:
            continue  # ended meanwhile
        fields = stat.rsplit(")", 1)[1].split()
        if fields[0] != "Z":  # a zombie runs nothing; subprocess reaps it
            found.add((pid, fields[19]))
    return frozenset(found)


def listening_sockets() -> frozenset[int]:
    """Inodes of the TCP sockets this process listens on. Each socket descriptor is asked
    (SO_ACCEPTCONN) through a duplicate: reading the kernel's tables (/proc/net/tcp) instead
    took ~10 ms of CPU a look, as they list every socket of the machine."""
    mine: set[int] = set()
    try:
        fds = os.listdir("/proc/self/fd")
    except OSError:
        return frozenset()
    for fd in fds:
        try:
            link = os.readlink(f"/proc/self/fd/{fd}")
        except OSError:
            continue
        if not link.startswith("socket:["):
            continue
        inode = int(link[8:-1])
        try:
            dup = os.dup(int(fd))
        except OSError:
            continue  # closed meanwhile
        with socket.socket(fileno=dup) as sock:  # closes the duplicate only
            if os.fstat(dup).st_ino != inode:
                continue  # the number was reused meanwhile
            if sock.family not in (socket.AF_INET, socket.AF_INET6):
                continue
            if sock.type != socket.SOCK_STREAM:
                continue
            if sock.getsockopt(socket.SOL_SOCKET, socket.SO_ACCEPTCONN):
                mine.add(inode)
    return frozenset(mine)


@dataclass(frozen=True)
class Snapshot:
    """What runs at one moment, outside asyncio."""

    threads: frozenset[threading.Thread]
    children: frozenset[tuple[int, str]]
    listening: frozenset[int]
    buses: frozenset[str]
    notifiers: int

    @classmethod
    def take(cls, listening: frozenset[int] | None = None) -> Snapshot:
        """What runs now; `listening`: these sockets instead of reading the kernel's tables
        (about 10 ms of CPU, most of the snapshot's cost), for a look at the rest only."""
        return cls(
            threads=frozenset(t for t in threading.enumerate() if t.is_alive()),
            children=child_processes(),
            listening=listening_sockets() if listening is None else listening,
            buses=frozenset(can.interfaces.virtual.channels),
            notifiers=len(can.Notifier._registry.pairs),
        )

    def left_since(self, before: Snapshot, owned: frozenset[threading.Thread]) -> list[str]:
        """What runs now that did not before, in words (empty: nothing); `owned`: threads
        something outliving the test owns and ends."""
        problems = []
        threads = sorted(
            (t for t in self.threads - before.threads - owned if not _pooled(t)),
            key=lambda t: t.name,
        )
        if threads:
            problems.append(f"threads left running: {threads}")
        if children := self.children - before.children:
            problems.append(f"child processes left running: {_describe(children)}")
        if sockets := self.listening - before.listening:
            problems.append(f"{len(sockets)} listening sockets left open")
        if buses := self.buses - before.buses:
            problems.append(f"virtual buses left open: {sorted(buses)}")
        if self.notifiers > before.notifiers:
            problems.append(
                f"{self.notifiers - before.notifiers} python-can Notifiers left running"
            )
        return problems


def _pooled(thread: threading.Thread) -> bool:
    """A worker of an event loop's thread pool: AnyIO's (Starlette runs sync endpoints there)
    or asyncio's default executor. Its loop owns it and ends it (AnyIO's also after 10 s idle);
    a gateway served for a whole module starts them during whichever test calls it first. A
    loop the test left running is caught by its own thread."""
    if type(thread).__name__ == "WorkerThread" and type(thread).__module__.startswith("anyio"):
        return True
    return thread.name.startswith("asyncio_")


def _describe(children: frozenset[tuple[int, str]]) -> list[str]:
    out = []
    for pid, _ in sorted(children):
        try:
            cmd = Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode()
        except OSError:
            cmd = "?"
        out.append(f"{pid}: {cmd[:200]}")
    return out


def executor_threads(loop: asyncio.AbstractEventLoop | None) -> frozenset[threading.Thread]:
    """The threads of `loop`'s default executor (`asyncio.to_thread`): the loop ends them as
    it closes, after this check."""
    executor = getattr(loop, "_default_executor", None)
    return frozenset(getattr(executor, "_threads", ()))


def settle(
    before: Snapshot,
    loop: asyncio.AbstractEventLoop | None = None,
    sleep: Callable[[float], None] = time.sleep,
) -> list[str]:
    """What the test left running, once `GRACE_S` has passed for it to end on its own."""
    deadline = time.monotonic() + GRACE_S
    pause = 0.02
    while True:
        owned = executor_threads(loop)
        # While a thread or a child is still ending, the sockets are not looked at: the
        # answer is "wait" either way. The last look, or one with nothing else left, is whole.
        rest = Snapshot.take(listening=before.listening).left_since(before, owned)
        if not rest or time.monotonic() > deadline:
            problems = Snapshot.take().left_since(before, owned)
            if not problems or time.monotonic() > deadline:
                return problems
        sleep(pause)
        # A clean test does not come here; one whose threads take seconds to end is polled
        # less often as it goes (each look reads /proc).
        pause = min(pause * 1.5, 0.2)


def tasks_left(loop: asyncio.AbstractEventLoop, before: set[asyncio.Task[object]]) -> list[str]:
    """Tasks of `loop` (not running) begun since `before` and not ended, after `TASK_GRACE_S` of
    running the loop for them to finish a cancellation already asked for."""

    def pending() -> list[asyncio.Task[object]]:
        me = asyncio.current_task(loop)
        return [t for t in asyncio.all_tasks(loop) if t not in before and t is not me]

    async def wait() -> None:
        deadline = time.monotonic() + TASK_GRACE_S
        while pending() and time.monotonic() < deadline:
            await asyncio.sleep(0.02)

    if pending():
        loop.run_until_complete(wait())
    if left := pending():
        return [f"tasks left running: {left}"]
    return []
