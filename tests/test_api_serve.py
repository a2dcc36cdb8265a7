"""`eqgw serve` as a user runs it: the first start prints an admin key once, never again."""

from __future__ import annotations

import os
import queue
import re
import socket
import subprocess
import threading
import time
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import httpx
import pytest
from sqlalchemy import create_engine, text

from tests.conftest import PG_ADMIN_URL
from tests.proc_helpers import ROOT, Process, eqgw, free_port, run, terminate, wait_until
from tests.support import web

KEY = re.compile(r"\beqgw_[A-Za-z0-9_-]{20,}")
SERVING = re.compile(r"serving on (http://\S+)")
LINK = re.compile(r"(http://[\d.:]+)/#login=([A-Za-z0-9_-]{20,})")


def _env(tmp_path: Path) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if not k.startswith("EQGW_")}
    return {
        **env,
        "PYTHONPATH": str(ROOT),
        "EQGW_DATABASE_URL": f"sqlite:///{tmp_path / 'eqgw.db'}",
    }


@contextmanager
def _serve(tmp_path: Path, port: int) -> Iterator[tuple[list[str], queue.Queue[str]]]:
    """`eqgw serve --simulate 1` in a subprocess; yields a list for lines seen and a line queue."""
    env = {
        **os.environ,
        "EQGW_DATABASE_URL": f"sqlite:///{tmp_path / 'eqgw.db'}",
        "EQGW_API_PORT": str(port),
        "PYTHONUNBUFFERED": "1",
    }
    env.pop("EQGW_CONFIG", None)
    proc = subprocess.Popen(
        eqgw("serve", "--simulate", "1"),
        cwd=tmp_path,
        env={**env, "PYTHONPATH": str(Path(__file__).resolve().parents[1])},
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    lines: queue.Queue[str] = queue.Queue()

    def pump() -> None:
        assert proc.stdout is not None
        for line in proc.stdout:
            lines.put(line)

    reader = threading.Thread(target=pump, daemon=True)
    reader.start()
    try:
        yield [], lines
    finally:
        terminate(proc)
        reader.join(timeout=10)
        assert proc.stdout is not None
        proc.stdout.close()


def _until_ready(port: int, lines: queue.Queue[str], seen: list[str], timeout: float = 60) -> None:
    """Collect output until the server answers /healthz (the key, if any, is printed before)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        try:
            while True:
                seen.append(lines.get_nowait())
        except queue.Empty:
            pass
        try:
            if web.get(f"http://127.0.0.1:{port}/healthz", timeout=2).status_code == 200:
                while not lines.empty():
                    seen.append(lines.get_nowait())
                return
        except httpx.TransportError:
            time.sleep(0.2)
    raise AssertionError("eqgw serve did not come up:\n" + "".join(seen))


def test_first_start_prints_the_admin_key_once(tmp_path: Path) -> None:
    """The admin key for the API, on its own line; for the dashboard a one-time login link,
    whose code logs in once; never a link carrying the key."""
    port = free_port()
    with _serve(tmp_path, port) as (seen, lines):
        _until_ready(port, lines, seen)
        out = "".join(seen)
        keys = set(KEY.findall(out))
        assert len(keys) == 1, out
        (key,) = keys
        assert out.count(key) == 1 and f"    {key}\n" in out, out
        assert "?key=" not in out, out
        links = LINK.findall(out)
        assert len(links) == 1 and links[0][0] == f"http://127.0.0.1:{port}", out
        code = links[0][1]
        base = f"http://127.0.0.1:{port}"
        r = web.post(f"{base}/api/v1/session", json={"code": code}, timeout=10)
        assert r.status_code == 201 and r.json()["role"] == "admin", r.text
        again = web.post(f"{base}/api/v1/session", json={"code": code}, timeout=10)
        assert again.status_code == 401, again.text
        r = web.get(
            f"http://127.0.0.1:{port}/api/v1/vehicles",
            headers={"Authorization": f"Bearer {key}"},
            timeout=10,
        )
        assert r.status_code == 200, r.text
        assert [v["id"] for v in r.json()["vehicles"]] == ["SIM-001"]
        # Another link, made by the CLI (another process) while the gateway runs, works on it.
        made = subprocess.run(
            eqgw("keys", "login-link", "1"),
            cwd=tmp_path,
            env={**_env(tmp_path), "EQGW_API_PORT": str(port)},
            capture_output=True,
            text=True,
            timeout=120,
        )
        assert made.returncode == 0, made.stderr
        (link,) = LINK.findall(made.stdout)
        assert link[0] == base and key not in made.stdout, made.stdout
        r = web.post(f"{base}/api/v1/session", json={"code": link[1]}, timeout=10)
        assert r.status_code == 201 and r.json()["name"] == "first admin", r.text

    port = free_port()
    with _serve(tmp_path, port) as (seen, lines):
        _until_ready(port, lines, seen)
        out = "".join(seen)
        assert SERVING.search(out), out
        assert not KEY.search(out) and "?key=" not in out and not LINK.search(out), out
        # The key printed the first time still works against the same database.
        r = web.get(
            f"http://127.0.0.1:{port}/api/v1/vehicles",
            headers={"Authorization": f"Bearer {key}"},
            timeout=10,
        )
        assert r.status_code == 200, r.text


def _run(tmp_path: Path, *args: str, env: dict[str, str] | None = None) -> Any:
    """`eqgw ARGS` to its end, on a SQLite file in `tmp_path` unless `env` says otherwise
    (forked from the test process's preloaded interpreter: tests/support/forked.py; `eqgw
    serve` above runs in an interpreter of its own, as a user starts it)."""
    full = {k: v for k, v in os.environ.items() if not k.startswith("EQGW_")}
    full.update({"PYTHONPATH": str(ROOT), "EQGW_DATABASE_URL": f"sqlite:///{tmp_path / 'eqgw.db'}"})
    full.update(env or {})
    return run(eqgw(*args), tmp_path, full, timeout=120)


def test_bad_starts_say_why_in_one_line_and_create_nothing(tmp_path: Path) -> None:
    for args, word in (
        (["serve", "--port", "99999"], "not a port"),
        (["serve", "--simulate", "-3"], "negative"),
        (["keys", "create", "--role", "viewer", "--name", "   "], "empty"),
        (["keys", "create", "--role", "viewer", "--name", "a\nb"], "control"),
        (["keys", "create", "--role", "viewer", "--name", "n" * 201], "at most 200"),
    ):
        r = _run(tmp_path, *args)
        assert r.returncode == 2 and word in r.stderr, (args, r.stderr)
        assert "Traceback" not in r.stderr + r.stdout, r.stderr
    # A port in use is said before anything is created: no database, no one-time key.
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        r = _run(tmp_path, "serve", "--simulate", "1", "--port", str(busy.getsockname()[1]))
    assert r.returncode == 2 and "cannot listen" in r.stderr, r.stderr
    assert "Traceback" not in r.stderr + r.stdout and not KEY.search(r.stdout + r.stderr)
    assert not (tmp_path / "eqgw.db").exists()
    # A SQLite file in a folder that does not exist can never work: said, not retried.
    missing = {"EQGW_DATABASE_URL": f"sqlite:///{tmp_path / 'no' / 'such' / 'x.db'}"}
    r = _run(tmp_path, "serve", "--port", "0", env=missing)
    assert r.returncode == 2 and "does not exist" in r.stderr and "Traceback" not in r.stderr
    # The keys commands on a database they cannot reach: one line, exit 1.
    away = {"EQGW_DATABASE_URL": "postgresql+psycopg://postgres@127.0.0.1:1/x"}
    r = _run(tmp_path, "keys", "list", env=away)
    assert r.returncode == 1 and "cannot be used" in r.stderr, r.stderr
    assert "Traceback" not in r.stderr


@pytest.mark.postgres
def test_serve_waits_for_its_database_and_answers_503_while_it_is_away(tmp_path: Path) -> None:
    """The database does not take connections yet at start: retried and said; then it
    does, served.
    Then it refuses connections for a while: what needs the database answers JSON 503s,
    /readyz says why, the fleet list answers from memory, the gateway goes on and serves
    again once the database is back."""
    admin = create_engine(PG_ADMIN_URL, isolation_level="AUTOCOMMIT")
    name = f"eqgw_late_{uuid.uuid4().hex[:8]}"
    url = PG_ADMIN_URL.rsplit("/", 1)[0] + f"/{name}"
    # (A database that does not exist is a fault no retry cures: tests/test_permanent_faults.)
    with admin.connect() as conn:
        conn.execute(text(f'CREATE DATABASE "{name}" ALLOW_CONNECTIONS false'))
    proc = Process(
        eqgw("serve", "--simulate", "1", "--port", "0"),
        tmp_path,
        env={
            "EQGW_DATABASE_URL": url,
            "EQGW_API_KEY_CACHE_S": "0",
            "EQGW_API_METRICS_TOKEN": "metrics-secret",
        },
    )
    try:
        proc.wait_line(re.compile(r"database is unreachable .*; retrying in 2 s"))
        with admin.connect() as conn:
            conn.execute(text(f'ALTER DATABASE "{name}" ALLOW_CONNECTIONS true'))
        base = proc.wait_line(SERVING).group(1)
        (key,) = set(KEY.findall(proc.output()))
        auth = {"Authorization": f"Bearer {key}"}
        assert web.get(f"{base}/api/v1/vehicles", headers=auth, timeout=10).status_code == 200

        def block(allow: bool) -> None:
            with admin.connect() as conn:
                conn.execute(text(f'ALTER DATABASE "{name}" ALLOW_CONNECTIONS {allow}'))
                if not allow:
                    conn.execute(
                        text(
                            "SELECT pg_terminate_backend(pid) FROM pg_stat_activity "
                            "WHERE datname = :n"
                        ),
                        {"n": name},
                    )

        before = len(proc.output())  # (a loaded machine may have failed a round before)
        block(False)
        r = wait_until(
            lambda: (
                (r := web.get(f"{base}/api/v1/keys", headers=auth, timeout=10)).status_code == 503
                and r
            ),
            what="a 503 while the database is away",
        )
        assert r.json()["type"] == "unavailable" and r.headers["Retry-After"], r.text
        # The live view and the fleet list answer from memory meanwhile (the key as last read).
        listing = web.get(f"{base}/api/v1/vehicles", headers=auth, timeout=10)
        assert listing.status_code == 200, listing.text
        ready = web.get(
            f"{base}/readyz", headers={"Authorization": "Bearer metrics-secret"}, timeout=10
        )
        assert ready.status_code == 503 and not ready.json()["database"]["ok"], ready.text

        def rounds_failed() -> bool:
            # Rounds of the command delivery, the writer and requests fail meanwhile.
            writer = web.get(
                f"{base}/readyz", headers={"Authorization": "Bearer metrics-secret"}, timeout=10
            ).json()["database"]["writer"]
            said = "command delivery round failed" in proc.output()
            return said and writer["consecutive_failures"] >= 3

        wait_until(rounds_failed, what="rounds failing while the database is away")
        block(True)
        wait_until(
            lambda: web.get(f"{base}/api/v1/vehicles", headers=auth, timeout=10).status_code == 200,
            what="the API back",
        )
        wait_until(
            lambda: web.get(f"{base}/readyz", timeout=10).status_code == 200, what="ready again"
        )
        wait_until(
            lambda: "command delivery resumed after" in proc.output()[before:],
            what="command delivery resumed",
        )
        out = proc.output()
        # Said, not flooded: one traceback of the command delivery, not one a round.
        said = [line for line in out.splitlines() if " WARNING " in line or " ERROR " in line]
        assert out[before:].count("command delivery round failed") == 1, "\n".join(said)
        assert "Internal Server Error" not in out
    finally:
        proc.stop()
        with admin.connect() as conn:
            conn.execute(text(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)'))
        admin.dispose()
