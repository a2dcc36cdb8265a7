"""The command line's conventions: --version, options after the command, logging, key masking."""

from __future__ import annotations

import json
import logging
import os
import re
from pathlib import Path
from typing import Any

import pytest

from eqgw.logs import configure_logging, redact
from tests.proc_helpers import ROOT, Process, eqgw, free_port, run
from tests.support import web

KEY = re.compile(r"\beqgw_[A-Za-z0-9_-]{20,}")


def _run(cwd: Path, *args: str, env: dict[str, str] | None = None) -> Any:
    full = {k: v for k, v in os.environ.items() if not k.startswith("EQGW_")}
    full.update({"PYTHONPATH": str(ROOT), **(env or {})})
    return run(eqgw(*args), cwd, full, timeout=120)


def test_version(tmp_path: Path) -> None:
    r = _run(tmp_path, "--version")
    assert r.returncode == 0, r.stderr
    assert re.fullmatch(r"eqgw \S+\n", r.stdout), r.stdout


def test_keys_take_config_and_db_before_or_after_the_action(tmp_path: Path) -> None:
    db = tmp_path / "fleet.db"
    config = tmp_path / "fleet.toml"
    config.write_text(f'database_url = "sqlite:///{db}"\n')
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()

    made = _run(
        elsewhere, "keys", "create", "--role", "viewer", "--name", "t", "--config", str(config)
    )
    assert made.returncode == 0, made.stderr
    # A new database is said on stderr (the key goes to the database the config names).
    assert "creating a new, empty one" in made.stderr
    assert not list(elsewhere.iterdir()), "nothing may be created in the current folder"
    for args in (
        ("keys", "list", "--config", str(config)),
        ("keys", "--config", str(config), "list"),
        ("keys", "list", "--db", f"sqlite:///{db}"),
        ("keys", "--db", f"sqlite:///{db}", "list"),
    ):
        r = _run(elsewhere, *args)
        assert r.returncode == 0, (args, r.stderr)
        assert "viewer" in r.stdout and " t\n" in r.stdout, (args, r.stdout)
        # An existing database is not announced.
        assert "creating" not in r.stderr, (args, r.stderr)
    # --db wins over the config's database.
    other = _run(elsewhere, "keys", "list", "--config", str(config), "--db", "sqlite:///other.db")
    assert other.returncode == 0 and "viewer" not in other.stdout, other.stdout
    assert "creating a new, empty one" in other.stderr


def test_a_key_made_in_the_wrong_folder_is_announced(tmp_path: Path) -> None:
    r = _run(tmp_path, "keys", "create", "--role", "admin", "--name", "ops")
    assert r.returncode == 0, r.stderr
    assert f"no database at {tmp_path / 'eqgw.db'}" in r.stderr
    assert "--config or --db" in r.stderr
    again = _run(tmp_path, "keys", "create", "--role", "admin", "--name", "ops2")
    assert again.returncode == 0 and "no database" not in again.stderr, again.stderr


def test_redact_masks_keys_and_key_parameters() -> None:
    key = "eqgw_" + "A1b2_C3d4-" * 4 + "xyz"
    assert key not in redact(f"GET /?key={key} HTTP/1.1")
    assert redact("GET /ws?key=abc&x=1") == "GET /ws?key=***&x=1"
    assert redact(f"Bearer {key}") == "Bearer eqgw_***"
    assert redact("nothing secret") == "nothing secret"


def test_redact_masks_percent_encoded_keys() -> None:
    """A key or a `key=` parameter hidden behind percent-encoding (as a client may send it, and
    the server decodes it) is masked too, once decoded."""
    key = "eqgw_" + "A1b2_C3d4-" * 4 + "xyz"
    hidden = key.replace("_", "%5F").replace("A", "%41")
    for line in (
        f"GET /?%6Bey={hidden} HTTP/1.1",
        f"GET /?%6B%65%79={hidden} HTTP/1.1",
        f"GET /?%256Bey=%2565qgw%255F{key[5:]} HTTP/1.1",  # encoded twice
        "GET /api/v1/ws?x=1&%6Bey=not-a-key-shape HTTP/1.1",
    ):
        out = redact(line)
        assert key[5:] not in out and "not-a-key-shape" not in out, (line, out)
        assert "***" in out, out
    assert redact("GET /api/v1/vehicles?vehicle=BUS%2D1") == "GET /api/v1/vehicles?vehicle=BUS%2D1"


def test_json_log_lines_carry_time_level_and_no_key(capsys: pytest.CaptureFixture[str]) -> None:
    root = logging.getLogger()
    saved = (list(root.handlers), root.level)
    try:
        configure_logging("info", "json")
        logging.getLogger("eqgw.test").warning("key %s used", "eqgw_" + "x" * 43)
        logging.getLogger("eqgw.test").debug("not shown at info")
    finally:
        root.handlers[:] = saved[0]
        root.setLevel(saved[1])
    lines = capsys.readouterr().err.splitlines()
    assert len(lines) == 1, lines
    record = json.loads(lines[0])
    assert record["level"] == "warning" and record["logger"] == "eqgw.test"
    assert record["message"] == "key eqgw_*** used"
    assert re.fullmatch(r"\d{4}-\d\d-\d\dT\d\d:\d\d:\d\d\.\d{3}Z", record["time"])


def test_serve_access_log_masks_the_key(tmp_path: Path) -> None:
    port = free_port()
    env = {"EQGW_DATABASE_URL": f"sqlite:///{tmp_path / 'eqgw.db'}"}
    proc = Process(
        eqgw("serve", "--port", str(port), "--access-log", "--log-format", "json"), tmp_path, env
    )
    try:
        key = proc.wait_line(KEY).group(0)
        proc.wait_line(re.compile("serving on"))
        base = f"http://127.0.0.1:{port}"
        assert web.get(f"{base}/api/v1/vehicles?key={key}", timeout=10).status_code == 401
        hidden = key.replace("_", "%5F")
        assert web.get(f"{base}/?%6Bey={hidden}", timeout=10).status_code in (200, 303)
        r = web.get(f"{base}/api/v1/me", headers={"Authorization": f"Bearer {key}"}, timeout=10)
        assert r.status_code == 200, r.text
        proc.wait_line(re.compile(r'"GET /api/v1/me HTTP/1.1\\" 200'))
    finally:
        proc.stop()
    access = [json.loads(line) for line in proc.lines if '"uvicorn.access"' in line]
    assert {a["level"] for a in access} == {"info"}, access
    assert any("/api/v1/vehicles?key=***" in a["message"] for a in access), access
    # The key appears only where serve prints it for the operator, never in a log record.
    logged = [line for line in proc.lines if line.startswith("{")]
    assert logged and not any(key in line for line in logged), logged
    assert not any(key[5:20] in line for line in logged), logged  # nor percent-encoded


def test_a_bad_log_level_from_the_environment_is_one_line_and_exit_2(tmp_path: Path) -> None:
    r = _run(tmp_path, "dbc", env={"EQGW_LOG_LEVEL": "verbose"})
    assert r.returncode == 2 and "log level 'verbose'" in r.stderr and "Traceback" not in r.stderr
    ok = _run(tmp_path, "dbc", env={"EQGW_LOG_LEVEL": "INFO"})
    assert ok.returncode == 0 and ok.stdout.startswith("VERSION"), ok.stderr
