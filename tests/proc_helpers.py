"""Real `eqgw` child processes for the tests and benches that run it as a user would."""

from __future__ import annotations

import contextlib
import os
import re
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]

# Set by tests/conftest.py: an `eqgw` command is forked from a server that imported eqgw once
# per test process (tests/support/forked.py) instead of a new interpreter. The benches, which
# measure new interpreters, leave it off.
FORK = False


@contextlib.contextmanager
def mounted(target: Path, *steps: list[str], what: str) -> Iterator[Path]:
    """`target` after `mount` ran with each of `steps`, unmounted afterwards (root only: the
    test is skipped, saying it could not mount `what`, where a step fails)."""
    for args in steps:
        done = subprocess.run(["mount", *args], capture_output=True, text=True)
        if done.returncode != 0:
            subprocess.run(["umount", "-l", str(target)], check=False, capture_output=True)
            import pytest

            pytest.skip(f"cannot mount {what} here: {done.stderr.strip()}")
    try:
        yield target
    finally:
        subprocess.run(["umount", "-l", str(target)], check=False)


def free_port() -> int:
    """A TCP port on 127.0.0.1 that nothing listens on right now."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port: int = s.getsockname()[1]
        return port


def wait_until(
    cond: Callable[[], Any], timeout: float = 60.0, what: str = "condition", interval: float = 0.05
) -> Any:
    """Poll `cond` until truthy (generous timeouts: the machine's cores are shared)."""
    deadline = time.monotonic() + timeout
    while True:
        value = cond()
        if value:
            return value
        if time.monotonic() > deadline:
            raise AssertionError(
                f"timed out after {timeout:g} s waiting for {what} (last: {value!r})"
            )
        time.sleep(interval)


def eqgw(*args: str) -> list[str]:
    """The command line of `eqgw ARGS` from this checkout."""
    return [sys.executable, "-m", "eqgw.cli", *args]


def _forked(argv: list[str], env: dict[str, str]) -> bool:
    """Whether `argv` (with `env`, the child's whole environment) runs forked: an `eqgw`
    command of this checkout, with nothing else on its Python path."""
    return FORK and argv[:3] == eqgw() and env.get("PYTHONPATH", str(ROOT)) == str(ROOT)


def popen(argv: list[str], cwd: Path | str, env: dict[str, str], *, stderr_apart: bool) -> Any:
    """`argv` started with its output piped (text; stderr into stdout unless `stderr_apart`):
    a `subprocess.Popen`, or its forked equivalent for an `eqgw` command (tests/support/
    forked.py)."""
    if _forked(argv, env):
        from tests.support import forked

        return forked.ForkedPopen(argv, cwd, env, stderr_apart=stderr_apart)
    return subprocess.Popen(
        argv,
        cwd=cwd,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE if stderr_apart else subprocess.STDOUT,
        text=True,
    )


def run(
    argv: list[str], cwd: Path | str, env: dict[str, str], timeout: float
) -> subprocess.CompletedProcess[str]:
    """`subprocess.run(argv, capture_output=True, text=True)` with `env` the child's whole
    environment, forked for an `eqgw` command (tests/support/forked.py)."""
    proc = popen(argv, cwd, env, stderr_apart=True)
    try:
        out, err = proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.communicate()
        raise
    return subprocess.CompletedProcess(argv, proc.returncode, out, err)


def terminate(proc: subprocess.Popen[Any]) -> None:
    """SIGTERM, then SIGKILL if the process has not ended within 30 s."""
    if proc.poll() is None:
        proc.terminate()
        try:
            proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(timeout=10)


class Process:
    """A child process with its output (stdout and stderr) collected line by line."""

    def __init__(self, argv: list[str], cwd: Path, env: dict[str, str] | None = None) -> None:
        # Nothing of this shell's EQGW_ settings leaks in; the caller's env is all there is.
        base = {k: v for k, v in os.environ.items() if not k.startswith("EQGW_")}
        full_env = {**base, "PYTHONUNBUFFERED": "1", "PYTHONPATH": str(ROOT), **(env or {})}
        self.argv = argv
        self.proc = popen(argv, cwd, full_env, stderr_apart=False)
        self.lines: list[str] = []
        self._pump = threading.Thread(target=self._read, daemon=True)
        self._pump.start()

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            self.lines.append(line)

    def output(self) -> str:
        return "".join(self.lines)

    def wait_line(self, pattern: re.Pattern[str], timeout: float = 60) -> re.Match[str]:
        """The first output line matching `pattern`; fails if the process ends without one."""

        def match() -> re.Match[str] | None:
            for line in list(self.lines):
                m = pattern.search(line)
                if m:
                    return m
            if self.proc.poll() is not None:
                raise AssertionError(f"{self.argv[3:4]} ended: {self.output()[-3000:]}")
            return None

        found: re.Match[str] = wait_until(match, timeout, f"{pattern.pattern!r} in the output")
        return found

    def kill(self) -> None:
        """SIGKILL: no cleanup at all, as a power cut or the OOM killer."""
        self.proc.send_signal(signal.SIGKILL)
        self.proc.wait(timeout=30)
        self._close()

    def stop(self) -> int:
        terminate(self.proc)
        self._close()
        return self.proc.returncode

    def _close(self) -> None:
        self._pump.join(timeout=10)
        if self.proc.stdout is not None:
            self.proc.stdout.close()
