"""Shutdown never hangs: `eqgw serve` under load ends within its bound on SIGTERM, the ingest's
final flush done, round after round; a stop() whose task ignores its cancel still returns."""

from __future__ import annotations

import asyncio
import os
import random
import re
import signal
import threading
import time
from pathlib import Path
from typing import Any

import httpx
import pytest
from sqlalchemy import create_engine

from eqgw.commands.service import CommandService
from eqgw.ingest.state import LiveState
from eqgw.store.migrate import upgrade_engine
from eqgw.tasks import cancel_and_wait
from eqgw.web.settings import ApiSettings
from tests.proc_helpers import Process, eqgw, free_port, wait_until
from tests.support import web

KEY = re.compile(r"\beqgw_[A-Za-z0-9_-]{20,}")
FLUSHED = "eqgw: stopping: final flush done, every row written"
BOUND_S = 9.0  # EQGW_API_SHUTDOWN_TIMEOUT_S, its default


def _load(port: int, key: str, stop: threading.Event, done: list[None]) -> None:
    """Reads, and requests the gateway delivers on the bus, until told to stop (`done` gets
    an item per request answered)."""
    auth = {"Authorization": f"Bearer {key}"}
    base = f"http://127.0.0.1:{port}/api/v1"
    rng = random.Random(port)
    with web.Client(timeout=5) as http:
        while not stop.is_set():
            try:
                http.get(f"{base}/vehicles", headers=auth)
                vehicle = f"SIM-00{rng.randint(1, 3)}"
                what = rng.choice(("dm1", "component_id", "software_id"))
                http.post(f"{base}/vehicles/{vehicle}/requests", json={"what": what},
                          headers=auth)  # fmt: skip
                done.append(None)
            except httpx.HTTPError:
                time.sleep(0.05)  # the server is going away


def sigterm_round(workdir: Path, load: int) -> tuple[float, int | None, str]:
    """Start `eqgw serve --simulate 3`, load it for `load` requests, SIGTERM it (at a moment
    with requests in flight, however fast the machine is): (seconds from the
    signal to the exit, exit code or None if it had not ended after the bound + 20 s, output)."""
    port = free_port()
    workdir.mkdir(parents=True, exist_ok=True)
    env = {"EQGW_DATABASE_URL": f"sqlite:///{workdir / 'eqgw.db'}"}
    gw = Process(eqgw("serve", "--simulate", "3", "--port", str(port)), workdir, env)
    stop = threading.Event()
    workers: list[threading.Thread] = []
    done: list[None] = []
    try:
        gw.wait_line(re.compile(r"serving on"), timeout=120)
        m = KEY.search(gw.output())  # a new database: its first start prints the admin key
        assert m, gw.output()
        key = m.group(0)
        workers = [threading.Thread(target=_load, args=(port, key, stop, done)) for _ in range(3)]
        for w in workers:
            w.start()
        wait_until(lambda: len(done) >= load, 120, f"{load} requests answered")
        gw.proc.send_signal(signal.SIGTERM)
        t0 = time.monotonic()
        try:
            rc: int | None = gw.proc.wait(timeout=BOUND_S + 20)
        except Exception:
            rc = None
        elapsed = time.monotonic() - t0
    finally:
        stop.set()
        for w in workers:
            w.join(timeout=10)
        if gw.proc.poll() is None:
            gw.kill()
        else:
            gw._close()
    return elapsed, rc, gw.output()


@pytest.mark.timeout(900)
def test_sigterm_under_load_ends_within_the_bound_with_the_final_flush(tmp_path: Path) -> None:
    rounds = int(os.environ.get("EQGW_SIGTERM_ROUNDS", "5"))
    rng = random.Random(7)
    for i in range(rounds):
        elapsed, rc, out = sigterm_round(tmp_path / f"round{i}", rng.randint(20, 80))
        # Not a timing goal (bench/shutdown.py prints those): a process still running at the
        # bound is ended by the watchdog (exit 3, stacks on stderr), one that hangs is killed.
        assert rc is not None, f"round {i}: still running {BOUND_S + 20:g} s after SIGTERM"
        assert rc in (0, -signal.SIGTERM), f"round {i}: exit {rc}: {out[-4000:]}"
        assert FLUSHED in out, f"round {i}: no final flush: {out[-4000:]}"
        assert "shutdown still running" not in out
        assert elapsed < BOUND_S + 5


async def test_stop_is_bounded_even_if_delivery_ignores_its_cancel(sqlite_url: str) -> None:
    engine = create_engine(sqlite_url)
    await asyncio.to_thread(upgrade_engine, engine)
    service = CommandService(engine, LiveState(), {}, {}, set, ApiSettings())
    await service.start()
    try:
        real = service._task
        assert real is not None
        assert await cancel_and_wait(real)
        release = asyncio.Event()

        async def stubborn() -> None:
            # What a dropped cancel leaves behind: a delivery loop that goes on.
            while not release.is_set():
                try:
                    await asyncio.sleep(0.05)
                except asyncio.CancelledError:
                    continue

        left: asyncio.Task[Any] = asyncio.create_task(stubborn())
        service._task = left
        try:
            await asyncio.sleep(0.1)  # it runs, inside its try
            t0 = time.monotonic()
            await service.stop()  # its bound: 5 s
            # Not a timing goal: without a bound it never returns.
            assert time.monotonic() - t0 < 30.0
            assert not left.done()  # left behind (logged); stop() itself returned
        finally:
            release.set()
            await asyncio.wait({left}, timeout=10)
        assert left.done()
    finally:
        engine.dispose()
