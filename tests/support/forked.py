"""`eqgw` commands run as child processes forked from a server that imported eqgw once.

A test that runs `eqgw serve` or `eqgw keys` as a user would starts a new Python process, and
most of what such a process costs is its imports: `python -m bench.startup` printed 2.35-2.80 s
of CPU for `import eqgw.main` of the 3.07-3.30 s a gateway took to be ready on this machine,
and a full run started about 160 such processes.
The standard library's forkserver (`multiprocessing`, start method "forkserver") starts one
server per test process that imports eqgw's command line and application once; each command
is then a fork of it: its own process, pid, signals, exit status, working directory,
environment and output pipe, running `eqgw.cli.main` with its arguments, as
`python -m eqgw.cli` does after its imports.

What differs from a new interpreter, and where that is tested instead: the modules are
imported before the command's environment is set (start-up, configuration and import order
are tested with new interpreters: tests/test_api_serve.py, tests/test_lazy_imports.py,
tests/test_packaging.py, the benches); `EQGW_TEST_FORK=0` runs every command in a new
interpreter instead.
"""

from __future__ import annotations

import multiprocessing
import multiprocessing.forkserver
import multiprocessing.process
import multiprocessing.reduction
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Sequence
from multiprocessing.context import ForkServerContext
from pathlib import Path
from typing import IO, Any

# What the server imports once: eqgw's command line and everything `eqgw serve` loads before it
# serves (a command that needs less, `eqgw keys`, finds more already loaded than its own
# process would have; nothing it does depends on that).
_PRELOAD = ["eqgw.cli", "eqgw.main"]
_lock = threading.Lock()
_context: ForkServerContext | None = None


def enabled() -> bool:
    """Whether commands are forked (the default) or run in new interpreters
    (`EQGW_TEST_FORK=0`); Linux only."""
    return os.environ.get("EQGW_TEST_FORK", "1") != "0" and sys.platform == "linux"


def _ctx() -> ForkServerContext:
    global _context
    with _lock:
        if _context is None:
            ctx = multiprocessing.get_context("forkserver")
            assert isinstance(ctx, ForkServerContext)
            ctx.set_forkserver_preload(_PRELOAD)
            _context = ctx
        return _context


def helper_pids() -> frozenset[int]:
    """The long-lived helpers of this test process: the fork server and multiprocessing's
    resource tracker (the server's companion)."""
    from multiprocessing import resource_tracker

    pids = {server_pid(), getattr(resource_tracker._resource_tracker, "_pid", None)}
    return frozenset(p for p in pids if p)


def server_pid() -> int | None:
    """The fork server's pid, once started (its children are this process's commands)."""
    pid: int | None = getattr(multiprocessing.forkserver._forkserver, "_forkserver_pid", None)
    return pid


class _Fd:
    """A file descriptor handed to the forked child (multiprocessing sends it over the
    server's socket and the child receives its own copy)."""

    def __init__(self, fd: int) -> None:
        self.fd = fd

    def __reduce__(self) -> tuple[Any, tuple[Any]]:
        return (_rebuild_fd, (multiprocessing.reduction.DupFd(self.fd),))


def _rebuild_fd(dup: Any) -> int:
    fd: int = dup.detach()
    return fd


def _run(argv: list[str], cwd: str, env: dict[str, str], out: int, err: int) -> None:
    """In the forked child: become `python -m eqgw.cli ARGV` in `cwd` with `env`."""
    os.dup2(out, 1)
    os.dup2(err, 2)
    os.close(out)
    if err != out:
        os.close(err)
    # The test's output pipe: line by line, as PYTHONUNBUFFERED gives a new interpreter.
    for stream in (sys.stdout, sys.stderr):
        stream.reconfigure(line_buffering=True, write_through=True)  # type: ignore[attr-defined]
    os.chdir(cwd)
    os.environ.clear()
    os.environ.update(env)
    time.tzset()
    sys.path[0] = cwd  # what `python -m` puts first
    import eqgw.cli

    sys.argv = [eqgw.cli.__file__, *argv]
    code: int = 0
    try:
        code = eqgw.cli.main(argv)
    except SystemExit as exc:
        if exc.code is None:
            code = 0
        elif isinstance(exc.code, int):
            code = exc.code
        else:
            sys.stderr.write(f"{exc.code}\n")
            code = 1
    finally:
        # What the interpreter does on its way out: non-daemon threads joined, exit handlers.
        threading._shutdown()  # type: ignore[attr-defined]
        import atexit

        atexit._run_exitfuncs()
        sys.stdout.flush()
        sys.stderr.flush()
    os._exit(code & 0xFF)


class ForkedPopen:
    """The part of `subprocess.Popen` the tests use, for a forked `eqgw` command."""

    def __init__(
        self,
        argv: Sequence[str],
        cwd: Path | str,
        env: dict[str, str],
        *,
        stderr_apart: bool = False,
        text: bool = True,
    ) -> None:
        self.args = list(argv)
        out_r, out_w = os.pipe()
        err_r, err_w = os.pipe() if stderr_apart else (None, out_w)
        proc = _ctx().Process(
            target=_run,
            args=(self.args[3:], str(cwd), dict(env), _Fd(out_w), _Fd(err_w)),
            name=" ".join(self.args[3:5]),
        )
        try:
            proc.start()
        finally:
            os.close(out_w)
            if err_r is not None:
                os.close(err_w)
        # Not one of multiprocessing's children to join when this process ends: the tests
        # stop theirs, and the leftovers check finds any that is not.
        multiprocessing.process._children.discard(proc)  # type: ignore[attr-defined]
        self._proc = proc
        assert proc.pid is not None
        self.pid: int = proc.pid
        mode = "r" if text else "rb"
        self.stdout: IO[Any] | None = open(out_r, mode)
        self.stderr: IO[Any] | None = open(err_r, mode) if err_r is not None else None
        self.stdin = None
        self.returncode: int | None = None
        self._readers: list[threading.Thread] | None = None
        self._outs: dict[str, Any] = {}

    def poll(self) -> int | None:
        if self.returncode is None:
            self.returncode = self._proc.exitcode
        return self.returncode

    def wait(self, timeout: float | None = None) -> int:
        if self.returncode is None:
            self._proc.join(timeout)
            if self.poll() is None:
                assert timeout is not None
                raise subprocess.TimeoutExpired(self.args, timeout)
        assert self.returncode is not None
        return self.returncode

    def send_signal(self, sig: int) -> None:
        if self.poll() is None:
            os.kill(self.pid, sig)

    def terminate(self) -> None:
        self.send_signal(signal.SIGTERM)

    def kill(self) -> None:
        self.send_signal(signal.SIGKILL)

    def communicate(self, timeout: float | None = None) -> tuple[Any, Any]:
        """Everything the command wrote, once it has ended (`subprocess.Popen.communicate`
        without input: called again after a timeout, it goes on waiting)."""
        if self._readers is None:
            self._readers = [
                threading.Thread(target=self._read_all, args=(name, stream), daemon=True)
                for name, stream in (("out", self.stdout), ("err", self.stderr))
                if stream is not None
            ]
            for t in self._readers:
                t.start()
        self.wait(timeout)
        for t in self._readers:
            t.join(timeout=30)
        for stream in (self.stdout, self.stderr):
            if stream is not None:
                stream.close()
        return self._outs.get("out"), self._outs.get("err")

    def _read_all(self, name: str, stream: IO[Any]) -> None:
        self._outs[name] = stream.read()
