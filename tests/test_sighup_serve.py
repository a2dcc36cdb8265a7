"""SIGHUP does not end `eqgw serve`: it says it ignores it (settings are read at start only;
vehicles are managed in the database) and goes on serving; SIGTERM still ends it cleanly.
Real process."""

from __future__ import annotations

import re
import signal
from pathlib import Path
from typing import Any

from tests.cluster_helpers import readyz, start_gateway
from tests.proc_helpers import wait_until

IGNORED = re.compile(r"SIGHUP ignored")


def test_sighup_is_ignored_with_a_log_line(tmp_path: Path) -> None:
    fleet = tmp_path / "fleet.toml"
    fleet.write_text("")
    gw, base = start_gateway(tmp_path, f"sqlite:///{tmp_path / 'eqgw.db'}", fleet, "hup")
    try:
        gw.wait_line(re.compile(r"serving on"), timeout=120)
        seen: list[dict[str, Any] | None] = [None]

        def answered() -> bool:
            seen[0] = readyz(base)
            return gw.proc.poll() is not None or bool((seen[0] or {}).get("ready"))

        for _ in range(2):  # once is not all: a second hangup is ignored too
            gw.proc.send_signal(signal.SIGHUP)
            try:
                wait_until(answered, 30, "an answer after SIGHUP")
            except AssertionError as exc:
                exc.add_note(f"last /readyz: {seen[0]}\n{gw.output()[-3000:]}")
                raise
            assert gw.proc.poll() is None, gw.output()[-3000:]
        wait_until(lambda: len(IGNORED.findall(gw.output())) == 2, 30, "two SIGHUP log lines")
        assert gw.stop() in (0, -signal.SIGTERM), gw.output()[-3000:]
    finally:
        if gw.proc.poll() is None:
            gw.stop()
