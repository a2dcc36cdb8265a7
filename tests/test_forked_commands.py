"""The tests' forked `eqgw` commands (tests/support/forked.py) behave as new processes do:
the same output and exit status, their own environment and folder, signals and a kill as a
process has them, and a command left running is one the leftovers check sees."""

from __future__ import annotations

import os
import re
import signal
import subprocess
from pathlib import Path

import pytest

from tests import proc_helpers
from tests.proc_helpers import ROOT, Process, eqgw, free_port, run
from tests.support import forked, leftovers

pytestmark = pytest.mark.skipif(not forked.enabled(), reason="EQGW_TEST_FORK=0")


def _env(**extra: str) -> dict[str, str]:
    base = {k: v for k, v in os.environ.items() if not k.startswith("EQGW_")}
    return {**base, "PYTHONPATH": str(ROOT), **extra}


def test_a_forked_command_answers_as_a_new_interpreter_does(tmp_path: Path) -> None:
    env = _env(EQGW_DATABASE_URL=f"sqlite:///{tmp_path / 'eqgw.db'}")
    for args in (["--version"], ["keys", "nonsense"], ["serve", "--port", "not-a-port"]):
        mine = run(eqgw(*args), tmp_path, env, timeout=120)
        new = subprocess.run(
            eqgw(*args), cwd=tmp_path, env=env, capture_output=True, text=True, timeout=120
        )
        assert proc_helpers._forked(eqgw(*args), env)
        assert (mine.returncode, mine.stdout, mine.stderr) == (
            new.returncode,
            new.stdout,
            new.stderr,
        ), args


def test_a_forked_command_has_its_own_folder_environment_and_exit(tmp_path: Path) -> None:
    """`eqgw keys create` writes the database its environment names, relative to its own
    folder; the test process's environment and folder are untouched."""
    folder = tmp_path / "here"
    folder.mkdir()
    cwd_before, env_before = os.getcwd(), dict(os.environ)
    made = run(
        eqgw("keys", "create", "--name", "ops", "--role", "viewer"),
        folder,
        _env(EQGW_DATABASE_URL="sqlite:///relative.db"),
        timeout=120,
    )
    assert made.returncode == 0, made.stderr
    assert re.search(r"eqgw_\S+", made.stdout)
    assert (folder / "relative.db").exists()
    assert (os.getcwd(), dict(os.environ)) == (cwd_before, env_before)


def test_signals_and_a_kill_reach_the_forked_gateway(tmp_path: Path) -> None:
    env = {"EQGW_DATABASE_URL": f"sqlite:///{tmp_path / 'eqgw.db'}"}
    port = free_port()
    gw = Process(eqgw("serve", "--simulate", "1", "--port", str(port)), tmp_path, env)
    assert type(gw.proc) is forked.ForkedPopen
    try:
        gw.wait_line(re.compile(r"serving on"))
        # Running, it is one of this test process's children for the leftovers check.
        assert gw.proc.pid in {pid for pid, _ in leftovers.child_processes()}
        gw.proc.send_signal(signal.SIGHUP)  # logged and ignored, as a new process does
        gw.wait_line(re.compile(r"SIGHUP ignored"))
        assert gw.proc.poll() is None
    finally:
        gw.kill()
    assert gw.proc.returncode == -signal.SIGKILL
    assert gw.proc.pid not in {pid for pid, _ in leftovers.child_processes()}
