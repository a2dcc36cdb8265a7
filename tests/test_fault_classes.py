"""Every retry loop tells a fault that heals from one that will not: the classifier, the
supervisor, and each loop against a real part that fails one way or the other (a receiver
answering 401 or 503, a Mosquitto refusing the credentials, a port nobody listens on, a
central refusing the forwarder's key), and a bug injected with monkeypatch."""

from __future__ import annotations

import asyncio
import dataclasses
import logging
import os
import pwd
import shutil
import socket
import sqlite3
import subprocess
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest
from sqlalchemy import Engine
from sqlalchemy.exc import OperationalError, StatementError

from eqgw.config import DeliverySettings, MqttSettings, Settings
from eqgw.forward.uploader import UploadRefused
from eqgw.notify import repository as q
from eqgw.notify.delivery import AlertDelivery
from eqgw.supervisor import FatalError, Supervisor
from eqgw.tasks import Refused, classify, heals, http_status_heals
from tests.api_helpers import wait_for
from tests.webhook_helpers import (
    ALLOW_LOOPBACK,
    SECRET,
    Receiver,
    add_alert,
    add_event,
    deliveries,
    make_hook,
)

PUBLIC = "http://eqgw.example:8000"


def _sqlite_error(code: int, msg: str) -> sqlite3.Error:
    exc = sqlite3.OperationalError(msg)
    exc.sqlite_errorcode = code  # type: ignore[attr-defined]
    return exc


def test_classify() -> None:
    """What heals (retried with backoff), what is fatal (the process ends), what is a bug or
    a refusal (the task stops, reported)."""
    locked = OperationalError("INSERT", {}, _sqlite_error(5, "database is locked"))
    assert heals(ConnectionRefusedError()) and heals(ConnectionResetError())
    assert heals(TimeoutError()) and heals(locked) and heals(OSError(28, "No space left"))
    assert heals(httpx.ConnectError("refused")) and heals(RuntimeError("unknown: retried"))
    assert heals(ValueError("bad data from outside"))

    corrupt = OperationalError("SELECT", {}, _sqlite_error(11, "malformed"))
    for exc in (corrupt, PermissionError(13, "Permission denied")):
        fault = classify(exc)
        assert not fault.heals and fault.fatal

    for bug in (TypeError("x"), AttributeError("x"), KeyError("x"), IndexError(0), NameError()):
        fault = classify(bug)
        assert (fault.heals, fault.fatal, fault.bug) == (False, False, True), bug
    # SQLAlchemy wrapping a bind parameter's TypeError: still a bug.
    assert classify(StatementError("bad param", "INSERT", {}, TypeError("x"))).bug
    # A KeyError met while handling a refused connection is not what was raised.
    try:
        try:
            {}["k"]
        except KeyError:
            raise ConnectionRefusedError() from None
    except ConnectionRefusedError as exc:
        assert heals(exc)

    refused = classify(Refused("not authorised"))
    assert (refused.heals, refused.fatal, refused.bug) == (False, False, False)
    assert not heals(UploadRefused(401, "unknown key")) and classify(UploadRefused(403, "")).fatal
    assert heals(UploadRefused(503, "database away")) and heals(UploadRefused(429, "slow down"))

    assert [s for s in (400, 401, 403, 404, 408, 410, 425, 429, 500, 503) if http_status_heals(s)]
    assert {s: http_status_heals(s) for s in (401, 404, 408, 429, 500, 503)} == {
        401: False, 404: False, 408: True, 429: True, 500: True, 503: True,
    }  # fmt: skip


async def test_supervisor_stops_a_bug_once_and_restarts_what_heals(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """A loop with a bug fails once (logged once with its traceback, reported failed, never
    restarted, the process not ended); a loop refused a connection is restarted; a failed
    non-critical task is reported as such."""
    fatal: list[FatalError] = []
    runs = {"bug": 0, "refused": 0}

    async def buggy() -> None:
        runs["bug"] += 1
        await asyncio.sleep(0)
        raise TypeError("unsupported operand type(s)")

    async def refused() -> None:
        runs["refused"] += 1
        _, port = _closed_port()
        await asyncio.open_connection("127.0.0.1", port)  # a real refused connection

    caplog.set_level(logging.WARNING, logger="eqgw.supervisor")
    async with Supervisor(backoff=(0.01, 0.05), on_fatal=fatal.append) as sup:
        sup.start("buggy", buggy, critical=False)
        sup.start("refused", refused)
        await wait_for(lambda: _async(runs["refused"] >= 3), what="restarts after refusals")
        st = sup.get("buggy")
        assert st is not None and st.state == "failed" and "TypeError" in (st.last_error or "")
        assert st.critical is False and st.restarts == 0
        assert sup.get("refused").state in ("backoff", "running")  # type: ignore[union-attr]
    assert runs["bug"] == 1 and fatal == []
    said = [r for r in caplog.records if "buggy" in r.getMessage()]
    assert len(said) == 1 and "not retried" in said[0].getMessage() and said[0].exc_info


def _closed_port() -> tuple[str, int]:
    """A local port nobody listens on (connections to it are refused)."""
    s = socket.socket()
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()
    return "127.0.0.1", port


async def _async(value: Any) -> Any:
    return value


# -- webhooks --------------------------------------------------------------------------------


def _delivery(engine: Engine, **kw: Any) -> AlertDelivery:
    settings = DeliverySettings(
        **{"poll_s": 0.05, "timeout_s": 5.0, "retry_initial_s": 0.1, "retry_max_s": 0.4} | kw
    )
    config = Settings(
        database_url="sqlite://", delivery=settings, webhook_allow_networks=ALLOW_LOOPBACK
    )
    return AlertDelivery(engine, config, PUBLIC)


async def test_a_webhook_refusing_with_401_is_reported_and_one_failing_with_503_retried(
    engine: Engine, caplog: pytest.LogCaptureFixture
) -> None:
    """Two real receivers: one answers 401 (its secret is wrong), the other 503. The 401 is
    said once, reported (/readyz `refusing`, `eqgw_webhook_refusing`) and tried only at the
    longest delay; the 503 is retried on the doubling backoff. Once the first receiver takes
    the secret, its events arrive (nothing was given up) and it is no longer reported."""
    refusing = Receiver("whsec_" + "w" * 40).start()  # verifies another secret: 401
    failing = Receiver(SECRET, status=503).start()
    bad = make_hook(engine, refusing.url, name="wrong-secret")
    down = make_hook(engine, failing.url, name="down")
    alert = add_alert(engine)
    event = add_event(engine, alert, "raised")
    caplog.set_level(logging.INFO, logger="eqgw.notify.delivery")
    gw = _delivery(engine, retry_initial_s=0.05, retry_max_s=5.0)
    await gw.start()
    try:
        hooks = gw.webhooks
        assert hooks is not None
        await wait_for(lambda: _async(failing.attempts_for(event) >= 3), what="503 retried")
        assert refusing.attempts_for(event) == 1  # tried again only after retry_max_s
        assert set(hooks.status()["refusing"]) == {"wrong-secret"}
        assert "401" in hooks.status()["refusing"]["wrong-secret"]
        (row,) = deliveries(engine, bad)
        assert row["state"] == "pending" and row["next_attempt_at"] - row["last_attempt_at"] >= 4.9
        (other,) = deliveries(engine, down)
        assert other["state"] == "pending" and other["last_status"] == 503
        gauge = next(m for m in gw.collector.collect() if m.name == "eqgw_webhook_refusing").samples
        assert [(s.labels["webhook"], s.value) for s in gauge] == [("wrong-secret", 1.0)]
        said = [r for r in caplog.records if "refuses deliveries" in r.getMessage()]
        assert len(said) == 1 and said[0].levelno == logging.ERROR

        refusing.secret = SECRET  # fixed at the receiver: the next try (5 s) goes in

        async def accepted() -> bool:
            return bool(refusing.accepted())

        await wait_for(accepted, timeout=30, what="the refused event delivered once fixed")
        await wait_for(lambda: _async(not hooks.refusing), what="no longer reported")
    finally:
        await gw.stop()
        refusing.stop()
        failing.stop()


async def test_a_bug_in_the_webhook_round_stops_it_once(
    engine: Engine, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    """A TypeError in a delivery round is not retried every poll for ever: said once with its
    traceback, the dispatcher stopped, reported in /readyz and /metrics."""

    def broken(*_a: Any, **_k: Any) -> Any:
        raise TypeError("fan_out() got an unexpected keyword argument")

    monkeypatch.setattr(q, "fan_out", broken)
    caplog.set_level(logging.WARNING, logger="eqgw.notify.delivery")
    gw = _delivery(engine)
    await gw.start()
    try:
        hooks = gw.webhooks
        assert hooks is not None
        await wait_for(lambda: _async(not hooks.running), what="the dispatcher stopped")
        status = gw.status()["webhooks"]
        assert status["running"] is False and "a bug: TypeError" in status["failed"]
        failed = [m for m in gw.collector.collect() if m.name == "eqgw_alert_delivery_failed"]
        values = {s.labels["loop"]: s.value for s in failed[0].samples}
        assert values == {"webhooks": 1.0, "mqtt": 0.0}
    finally:
        await gw.stop()
    said = [r for r in caplog.records if "webhook delivery" in r.getMessage()]
    assert len(said) == 1 and said[0].exc_info and "not retried" in said[0].getMessage()
    assert hooks.counters["errors"] == 1


# -- MQTT ------------------------------------------------------------------------------------


@pytest.fixture
def auth_broker(tmp_path: Path) -> Iterator[tuple[int, str, str]]:
    """A Mosquitto of this test's own that wants a user name and password: (port, user,
    password). The shared broker on 1883 lets anyone in."""
    mosquitto = shutil.which("mosquitto") or "/usr/sbin/mosquitto"
    if not Path(mosquitto).exists() or not shutil.which("mosquitto_passwd"):
        pytest.skip("mosquitto and mosquitto_passwd are not installed")
    passwords = tmp_path / "passwords"
    subprocess.run(
        ["mosquitto_passwd", "-b", "-c", str(passwords), "eqgw", "right"],
        check=True,
        capture_output=True,
    )
    passwords.chmod(0o600)
    _, port = _closed_port()
    conf = tmp_path / "mosquitto.conf"
    user = pwd.getpwuid(os.geteuid()).pw_name
    conf.write_text(
        f"listener {port} 127.0.0.1\nallow_anonymous false\npassword_file {passwords}\n"
        f"user {user}\npersistence false\n"
    )
    log_file = tmp_path / "mosquitto.log"
    with log_file.open("wb") as out:
        proc = subprocess.Popen([mosquitto, "-c", str(conf)], stdout=out, stderr=out)
    try:
        deadline = time.monotonic() + 10
        while True:
            try:
                socket.create_connection(("127.0.0.1", port), timeout=0.5).close()
                break
            except OSError:
                if proc.poll() is not None or time.monotonic() > deadline:
                    pytest.fail(f"mosquitto did not start: {log_file.read_text()}")
                time.sleep(0.05)
        yield port, "eqgw", "right"
    finally:
        proc.terminate()
        proc.wait(10)


async def test_mqtt_wrong_credentials_stop_reconnecting(
    engine: Engine, auth_broker: tuple[int, str, str], caplog: pytest.LogCaptureFixture
) -> None:
    """A real broker refusing the password: the alert publisher says so once, stops paho's
    reconnecting and reports it failed; with the right password it connects."""
    from eqgw.notify.mqtt import MqttPublisher

    port, user, password = auth_broker
    caplog.set_level(logging.WARNING, logger="eqgw.notify.mqtt")
    settings = DeliverySettings(poll_s=0.05)

    def publisher(pw: str) -> MqttPublisher:
        mqtt = MqttSettings(
            host="127.0.0.1", port=port, username=user, password=pw, reconnect_min_s=0.1,
            reconnect_max_s=0.2,
        )  # fmt: skip
        return MqttPublisher(engine, mqtt, settings, PUBLIC)

    wrong = publisher("wrong")
    await wrong.start()
    try:
        await wait_for(lambda: _async(wrong.failed is not None), what="the refusal noticed")
        client = wrong._client
        assert client is not None
        # paho's network thread ends instead of trying again every 0.1-0.2 s.
        await wait_for(
            lambda: _async(client._thread is None or not client._thread.is_alive()),
            what="paho's thread ended",
        )
        assert wrong.connected is False and "not retried" in (wrong.failed or "")
        assert "Bad user name or password" in (wrong.failed or "") or "Not authorized" in (
            wrong.failed or ""
        )
    finally:
        await wrong.stop()
    said = [r for r in caplog.records if "refused by the broker" in r.getMessage()]
    assert len(said) == 1 and said[0].levelno == logging.ERROR

    right = publisher(password)
    await right.start()
    try:
        await wait_for(lambda: _async(right.connected), what="connected with the password")
        assert right.failed is None
    finally:
        await right.stop()


# -- the forwarder's uploader ------------------------------------------------------------------


async def test_uploader_retries_a_refused_connection_and_ends_on_a_refused_key(
    tmp_path: Path,
) -> None:
    """Against a port nobody listens on the uploader backs off and keeps trying; against a
    central answering 401 (its key unknown) it raises, and its supervisor ends the process."""
    from eqgw.forward.buffer import FrameBuffer
    from eqgw.forward.uploader import Uploader, UploadSettings

    buffer = FrameBuffer(tmp_path / "fwd.db")
    try:
        buffer.add([(time.time(), 0x18FFD41E, b"\x00" * 8, 0)])
        host, port = _closed_port()
        settings = UploadSettings(
            url=f"http://{host}:{port}/api/v1", key="k" * 32, vehicle="V", bus="V/can0",
            equalizer_sas=(30,), backoff_initial_s=0.01, backoff_max_s=0.05,
        )  # fmt: skip
        up = Uploader(buffer, settings)
        task = asyncio.create_task(up.run())
        try:
            await wait_for(lambda: _async(up.status().consecutive_failures >= 3), what="retries")
            assert not task.done() and "ConnectError" in (up.status().last_error or "")
        finally:
            task.cancel()
            await asyncio.gather(task, return_exceptions=True)

        refusing = Receiver("unused", status=401).start()  # any POST: 401
        try:
            settings = dataclasses.replace(settings, url=f"http://127.0.0.1:{refusing.port}")
            fatal: list[FatalError] = []
            async with Supervisor(backoff=(0.01, 0.05), on_fatal=fatal.append) as sup:
                sup.start("upload", Uploader(buffer, settings).run)
                await wait_for(lambda: _async(bool(fatal)), what="the refused key ends it")
            assert "HTTP 401" in str(fatal[0]) and sup.get("upload").state == "failed"  # type: ignore[union-attr]
            assert len(refusing.requests) == 1  # not tried again
        finally:
            refusing.stop()
    finally:
        buffer.close()


# -- the websocket's re-check of its credentials ------------------------------------------------


async def test_websocket_recheck_retries_the_database_and_ends_on_a_bug(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    from eqgw.api import ws

    monkeypatch.setattr(ws, "KEY_RECHECK_S", 0.01)
    monkeypatch.setattr(ws, "KEY_RECHECK_MAX_S", 0.05)
    calls = 0

    async def away_then_revoked() -> str | None:
        nonlocal calls
        calls += 1
        if calls < 4:
            _, port = _closed_port()
            await asyncio.open_connection("127.0.0.1", port)  # the database away: refused
        return "revoked"

    async with asyncio.timeout(30):
        assert await ws._watch(away_then_revoked, "key") == "revoked"
    assert calls == 4

    async def buggy() -> str | None:
        raise AttributeError("'NoneType' object has no attribute 'allows'")

    async with asyncio.timeout(30):
        assert await ws._watch(buggy, "key") == ws.CHECK_BROKEN_REASON
