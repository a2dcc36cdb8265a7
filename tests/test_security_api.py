"""Security of the API in process, on both engines: browser sessions and CSRF, headers, text the
database cannot store, webhook destinations and redaction, what anonymous callers read."""

from __future__ import annotations

import ipaddress
import logging
import re
from pathlib import Path
from typing import Any

import httpx
import pytest

from eqgw.notify import repository as wq
from eqgw.notify.destinations import check_url, parse_networks, redact_url, refusal
from tests.api_helpers import Served, heap_frozen, served, wait_for
from tests.webhook_helpers import Receiver, add_alert, add_event

V = "/api/v1/vehicles"
COOKIE = "eqgw_session"


def _cookie_attrs(response: httpx.Response) -> str:
    (header,) = [v for k, v in response.headers.multi_items() if k == "set-cookie"]
    return header.lower()


def _browser(s: Served) -> httpx.AsyncClient:
    """A client of its own (its own cookie jar), like a browser."""
    return httpx.AsyncClient(transport=httpx.ASGITransport(app=s.app), base_url="http://test")


async def _login(client: httpx.AsyncClient, key: str) -> str:
    """Log `client` in (it then holds a session cookie, no key); the session's CSRF token."""
    r = await client.post("/api/v1/session", json={"key": key})
    assert r.status_code == 201, r.text
    csrf: str = r.json()["csrf_token"]
    return csrf


# -- browser sessions ---------------------------------------------------------------------


async def test_session_cookie_stands_for_the_key_until_logout_or_revocation(db_url: str) -> None:
    async with served(db_url, vehicles=1) as s:
        operator = await s.key("operator")
        r = await s.client.post("/api/v1/session", json={"key": operator})
        attrs = _cookie_attrs(r)
        assert attrs.startswith(f"{COOKIE}=") and "httponly" in attrs, attrs
        assert "samesite=strict" in attrs and "path=/" in attrs, attrs
        assert "secure" not in attrs  # plain http here; https or an https public URL adds it
        assert operator not in attrs  # the cookie is a session token, not the key

        async with _browser(s) as browser:
            csrf = await _login(browser, operator)
            me = (await browser.get("/api/v1/session")).json()
            assert me["role"] == "operator" and me["csrf_token"] == csrf
            assert (await browser.get(V)).status_code == 200  # reads by cookie
            # A write by cookie needs the session's CSRF token (another site cannot send it).
            cmd = f"{V}/SIM-001/commands"
            r = await browser.post(cmd, json={"jump_start_override": True})
            assert r.status_code == 403 and r.json()["type"] == "csrf", r.text
            r = await browser.post(
                cmd, json={"jump_start_override": True}, headers={"X-CSRF-Token": "nope"}
            )
            assert r.status_code == 403
            r = await browser.post(
                cmd, json={"jump_start_override": True}, headers={"X-CSRF-Token": csrf}
            )
            assert r.status_code in (201, 202), r.text
            audit = (await s.client.get("/api/v1/audit", headers=s.auth())).json()["entries"]
            assert any(e["status_code"] == 403 and "CSRF" in (e["detail"] or "") for e in audit)

            # Logout ends the session on the server: the same cookie is refused afterwards.
            token = browser.cookies[COOKIE]
            assert (await browser.delete("/api/v1/session")).status_code == 403  # no CSRF
            r = await browser.delete("/api/v1/session", headers={"X-CSRF-Token": csrf})
            assert r.status_code == 204
            replay = {"Cookie": f"{COOKIE}={token}"}
            assert (await s.client.get(V, headers=replay)).status_code == 401
            assert (await s.client.get("/api/v1/session", headers=replay)).status_code == 401

        # Revoking the key ends every session of it.
        async with _browser(s) as browser:
            await _login(browser, operator)
            assert (await browser.get(V)).status_code == 200
            keys = (await s.client.get("/api/v1/keys", headers=s.auth())).json()
            kid = next(k["id"] for k in keys if k["role"] == "operator")
            assert (await s.client.delete(f"/api/v1/keys/{kid}", headers=s.auth())).is_success
            assert (await browser.get(V)).status_code == 401

        # Unknown keys and ingest keys get no session.
        r = await s.client.post("/api/v1/session", json={"key": "eqgw_not_a_key"})
        assert r.status_code == 401 and "set-cookie" not in r.headers
        body = {"name": "fwd", "role": "ingest", "scope": {"vehicles": ["SIM-001"]}}
        ingest = (await s.client.post("/api/v1/keys", json=body, headers=s.auth())).json()["key"]
        r = await s.client.post("/api/v1/session", json={"key": ingest})
        assert r.status_code == 403 and "set-cookie" not in r.headers


async def test_a_key_in_the_url_logs_no_one_in(db_url: str) -> None:
    """`/?key=...` (an old link, or another site's link to the attacker's key) opens no
    session: the answer is a redirect to the address without the key, and no cookie."""
    async with served(db_url, vehicles=1) as s:
        for key in (s.admin_key, "eqgw_wrong"):
            r = await s.client.get(f"/?key={key}&x=1")
            assert r.status_code == 303, r.text
            assert r.headers["location"] == "/?x=1"
            assert r.headers["referrer-policy"] == "no-referrer"
            assert "set-cookie" not in r.headers, r.headers


async def _key_id(s: Served, key: str) -> int:
    me = await s.client.post("/api/v1/session", json={"key": key})
    assert me.status_code == 201, me.text
    key_id: int = me.json()["key_id"]
    return key_id


async def test_a_login_code_works_once_within_its_time(db_url: str) -> None:
    from eqgw.security.login_codes import create_login_code

    async with served(db_url, vehicles=1) as s:
        admin_id = await _key_id(s, s.admin_key)
        code = await s.rt.db(create_login_code, admin_id, 600)
        assert code not in (s.admin_key,) and not code.startswith("eqgw_")
        # Asking whom a code is for does not use it up.
        r = await s.client.post("/api/v1/session/code", json={"code": code})
        assert r.status_code == 200 and r.json()["name"] == "first admin", r.text
        assert r.json()["role"] == "admin" and "set-cookie" not in r.headers
        async with _browser(s) as browser:
            r = await browser.post("/api/v1/session", json={"code": code})
            assert r.status_code == 201, r.text
            assert (await browser.get("/api/v1/session")).json()["role"] == "admin"
        # Once only, whoever tries it next.
        again = await s.client.post("/api/v1/session", json={"code": code})
        assert again.status_code == 401 and "set-cookie" not in again.headers
        assert (await s.client.post("/api/v1/session/code", json={"code": code})).status_code == 401
        # The database holds the code's hash only.
        from sqlalchemy import text

        with s.rt.engine.connect() as conn:
            stored = conn.execute(text("SELECT code_hash FROM login_codes")).scalars().all()
        assert code not in stored
        # Expired (made with no time to live), or for a key revoked since: no session.
        stale = await s.rt.db(create_login_code, admin_id, -1)
        r = await s.client.post("/api/v1/session", json={"code": stale})
        assert r.status_code == 401
        viewer = await s.key("viewer")
        viewer_id = await _key_id(s, viewer)
        code = await s.rt.db(create_login_code, viewer_id, 600)
        assert (await s.client.delete(f"/api/v1/keys/{viewer_id}", headers=s.auth())).is_success
        s.rt.keys.forget()
        assert (await s.client.post("/api/v1/session", json={"code": code})).status_code == 401
        # A key and a code at once, or neither: a 422.
        r = await s.client.post("/api/v1/session", json={"key": s.admin_key, "code": "x" * 20})
        assert r.status_code == 422
        assert (await s.client.post("/api/v1/session", json={})).status_code == 422


async def test_a_login_from_another_site_is_refused(db_url: str) -> None:
    """Login CSRF: a login (key or code) sent by another site's page is a 403, whatever it
    carries; the browser says where a request comes from (Sec-Fetch-Site, Origin)."""
    from eqgw.security.login_codes import create_login_code

    async with served(db_url, vehicles=1) as s:
        admin_id = await _key_id(s, s.admin_key)
        code = await s.rt.db(create_login_code, admin_id, 600)
        for headers in (
            {"Sec-Fetch-Site": "cross-site"},
            {"Sec-Fetch-Site": "same-site"},
            {"Origin": "http://evil.example"},
            {"Origin": "null"},
        ):
            for body in ({"key": s.admin_key}, {"code": code}):
                r = await s.client.post("/api/v1/session", json=body, headers=headers)
                assert r.status_code == 403, (headers, r.text)
                assert "set-cookie" not in r.headers
        # The code was not used up by the refused attempts; the gateway's own page may log in.
        own = {"Sec-Fetch-Site": "same-origin", "Origin": "http://test"}
        r = await s.client.post("/api/v1/session", json={"code": code}, headers=own)
        assert r.status_code == 201, r.text


# -- headers ------------------------------------------------------------------------------


async def test_every_page_and_file_carries_the_security_headers(sqlite_url: str) -> None:
    async with served(sqlite_url, vehicles=1) as s:
        for path in ("/", "/static/js/main.js", "/static/css/app.css", V, "/nope", "/healthz"):
            r = await s.client.get(path, headers=s.auth())
            h = r.headers
            assert h["x-content-type-options"] == "nosniff", path
            assert h["referrer-policy"] == "no-referrer", path
            csp = h["content-security-policy"]
            directives = {d.split()[0]: d.split()[1:] for d in csp.split("; ")}
            assert directives["script-src"] == ["'self'"], csp  # no inline script
            assert directives["frame-ancestors"] == ["'none'"], csp
        page = (await s.client.get("/")).text
        assert not re.search(r"<script(?![^>]*\bsrc=)", page), "inline script in index.html"
        assert " style=" not in page


async def test_docs_can_be_switched_off(sqlite_url: str, tmp_path: Path) -> None:
    async with served(sqlite_url, vehicles=1, docs=False) as s:
        assert (await s.client.get("/docs")).status_code == 404
        assert (await s.client.get("/openapi.json")).status_code == 404
    async with served(f"sqlite:///{tmp_path / 'other.db'}", vehicles=1) as s:
        assert (await s.client.get("/docs")).status_code == 200


# -- text the database cannot store ---------------------------------------------------------


async def test_nul_and_lone_surrogates_anywhere_are_422(db_url: str) -> None:
    async with served(db_url, vehicles=1) as s:
        auth = s.auth()
        for path in (
            f"{V}/SIM-001/faults?code=%00",
            "/api/v1/commands/%00",
            f"{V}/%00",
            f"{V}/SIM-001/history?unit=%00",
            "/api/v1/audit?action=a%00b",
            "/api/v1/alerts?rule=%00",
        ):
            r = await s.client.get(path, headers=auth)
            assert r.status_code == 422, (path, r.status_code, r.text)
            assert r.json()["type"] == "validation_error"
        # A key name with a lone surrogate (valid JSON, not storable text).
        raw = b'{"name": "bad \\ud800 name", "role": "viewer"}'
        r = await s.client.post(
            "/api/v1/keys", content=raw, headers={**auth, "Content-Type": "application/json"}
        )
        assert r.status_code == 422, r.text
        keys = (await s.client.get("/api/v1/keys", headers=auth)).json()
        assert not any("bad" in k["name"] for k in keys)


async def test_nan_and_infinity_in_alert_rule_params_are_refused(db_url: str) -> None:
    async with served(db_url, vehicles=1) as s:
        headers = {**s.auth(), "Content-Type": "application/json"}
        for literal in (b"NaN", b"Infinity", b"-Infinity"):
            r = await s.client.patch(
                "/api/v1/alerts/rules/overvoltage",
                content=b'{"params": {"fire_v24": ' + literal + b"}}",
                headers=headers,
            )
            assert r.status_code == 422, (literal, r.text)
        rule = (await s.client.get("/api/v1/alerts/rules/overvoltage", headers=s.auth())).json()
        assert rule["params"]["fire_v24"] == 30.0, rule


def test_rule_validation_refuses_non_finite_numbers() -> None:
    from eqgw.alerts.rules import validate_rule

    assert validate_rule("overvoltage", "warning", {"fire_v24": 30.0, "clear_v24": 29.0}) == []
    problems = validate_rule("overvoltage", "warning", {"fire_v24": float("nan"), "clear_v24": 29})
    assert problems and "finite" in problems[0]


# -- webhooks: destinations and redaction ----------------------------------------------------


@pytest.mark.parametrize(
    ("address", "refused"),
    [
        ("127.0.0.1", True),
        ("::1", True),
        ("169.254.169.254", True),
        ("10.1.2.3", True),
        ("192.168.0.10", True),
        ("172.16.5.5", True),
        ("100.64.0.1", True),
        ("0.0.0.0", True),
        ("::ffff:127.0.0.1", True),
        ("fd00:ec2::254", True),
        ("8.8.8.8", False),
        ("2606:4700:4700::1111", False),
    ],
)
def test_refused_destinations(address: str, refused: bool) -> None:
    ip = ipaddress.ip_address(address)
    assert (refusal(ip) is not None) is refused
    assert refusal(ip, parse_networks("0.0.0.0/0,::/0")) is None


async def test_names_are_checked_after_resolution() -> None:
    none = parse_networks("")
    for url in (
        "http://0x7f000001/",
        "http://localhost:8080/x",
        "http://[::1]/",
        "http://2130706433/",
    ):
        assert await check_url(url, none) is not None, url
    assert await check_url("http://127.0.0.1/", parse_networks("127.0.0.0/8")) is None


def test_redaction() -> None:
    assert redact_url("https://user:pw@hooks.example.com/in?token=abc&x=1") == (
        "https://***@hooks.example.com/in?token=***&x=***"
    )
    assert redact_url("https://hooks.slack.com/services/T000/B000/XXXXSECRET") == (
        "https://hooks.slack.com/services/T000/B000/***"
    )
    assert "SECRET" not in redact_url("https://chat.example/hooks/SECRET", "slack")
    assert redact_url("https://receiver.example/alerts") == "https://receiver.example/alerts"


async def test_webhooks_refuse_internal_destinations_by_default(db_url: str) -> None:
    receiver = Receiver("whsec_" + "s" * 40, status=500).start()
    try:
        async with served(db_url, vehicles=1) as s:
            auth = s.auth()
            for url in (
                receiver.url,
                "http://[::1]:9/",
                "http://169.254.169.254/latest/meta-data/",
                "http://0x7f000001:9/",
                "http://localhost:9/",
            ):
                r = await s.client.post(
                    "/api/v1/webhooks", json={"name": "in", "url": url}, headers=auth
                )
                assert r.status_code == 422, (url, r.text)
                assert r.json()["type"] == "destination_refused"
            # One stored before the check (or a name that resolves elsewhere later): the
            # delivery refuses it at connection time, and the receiver hears nothing.
            with s.rt.engine.begin() as conn:
                hook_id = wq.create_webhook(
                    conn,
                    {"name": "old", "url": receiver.url, "secret": receiver.secret,
                     "format": "json", "enabled": True, "created_at": 0.0, "updated_at": 0.0},
                )  # fmt: skip
            r = await s.client.post(f"/api/v1/webhooks/{hook_id}/test", headers=auth)
            assert r.status_code == 200, r.text
            result = r.json()
            assert result["delivered"] is False and "loopback" in result["error"], result
            assert receiver.requests == []
    finally:
        receiver.stop()


async def test_allowed_receivers_body_never_echoed_and_urls_redacted(
    db_url: str, caplog: pytest.LogCaptureFixture
) -> None:
    receiver = Receiver("whsec_" + "s" * 40, status=500).start()
    receiver.reply = b"INTERNAL-PAGE-CONTENT"
    config = {"webhook_allow_networks": "127.0.0.0/8"}
    try:
        async with served(db_url, vehicles=1, config=config) as s:
            auth = s.auth()
            url = receiver.url.replace("http://", "http://ops:hunter2@") + "?token=tok123"
            r = await s.client.post(
                "/api/v1/webhooks",
                json={"name": "lan", "url": url, "secret": receiver.secret},
                headers=auth,
            )
            assert r.status_code == 201, r.text
            hook = r.json()
            assert "hunter2" not in hook["url"] and "tok123" not in hook["url"], hook
            r = await s.client.post(f"/api/v1/webhooks/{hook['id']}/test", headers=auth)
            result = r.json()
            assert result["delivered"] is False and result["status"] == 500, result
            assert len(receiver.requests) == 1  # allowed: it was reached
            seen: list[Any] = [
                r.text,
                (await s.client.get("/api/v1/webhooks", headers=auth)).text,
                (await s.client.get(f"/api/v1/webhooks/{hook['id']}", headers=auth)).text,
                (
                    await s.client.get(f"/api/v1/webhooks/{hook['id']}/deliveries", headers=auth)
                ).text,
                (await s.client.get("/readyz", headers=auth)).text,
                (await s.client.get("/api/v1/audit", headers=auth)).text,
            ]
            for text in seen:
                assert "INTERNAL-PAGE-CONTENT" not in text
                assert "hunter2" not in text and "tok123" not in text
            # A failing delivery's log line names the webhook without its credentials.
            caplog.set_level(logging.WARNING, logger="eqgw.notify.delivery")
            alert = add_alert(s.rt.engine)
            add_event(s.rt.engine, alert, "raised")
            s.app.state.delivery.wake()

            async def logged() -> bool:
                return any("lan" in rec.getMessage() for rec in caplog.records)

            await wait_for(logged, what="the failed delivery logged")
            for rec in caplog.records:
                assert "hunter2" not in rec.getMessage() and "tok123" not in rec.getMessage()
    finally:
        receiver.stop()


# -- what anonymous callers read ---------------------------------------------------------------


async def test_readyz_and_metrics_without_credentials_say_little(db_url: str) -> None:
    async with served(db_url, vehicles=1, metrics_token="scrape-me") as s:
        r = await s.client.get("/readyz")
        assert r.status_code == 200 and r.json() == {"ready": True}, r.text
        viewer = await s.key("viewer")
        assert (await s.client.get("/readyz", headers=s.auth(viewer))).json() == {"ready": True}
        for auth in (s.auth(), {"Authorization": "Bearer scrape-me"}):
            full = (await s.client.get("/readyz", headers=auth)).json()
            assert "buses" in full and "alerts" in full, full

        anon = (await s.client.get("/metrics")).text
        assert "eqgw_frames_total" in anon  # what a Prometheus needs
        assert "SIM-001" not in anon and 'bus="' not in anon, anon
        full_m = (
            await s.client.get("/metrics", headers={"Authorization": "Bearer scrape-me"})
        ).text
        assert 'bus="SIM-001' in full_m
        assert "SIM-001" in (await s.client.get("/metrics", headers=s.auth())).text


# -- the websocket: by cookie from the gateway's own pages, or a first message -----------------


def test_websocket_by_cookie_origin_first_message_and_logout(db_url: str) -> None:
    import warnings

    from starlette.websockets import WebSocketDisconnect

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        from starlette.testclient import TestClient

    from eqgw.config import Settings
    from eqgw.main import create_app
    from eqgw.sim.clock import RealtimeClock
    from eqgw.sim.fleet import SimulatedFleet
    from eqgw.web.settings import ApiSettings
    from tests.test_api_ws import _recv

    keys: list[str] = []
    app = create_app(
        Settings(database_url=db_url),
        api=ApiSettings(),
        sim=SimulatedFleet(1, seed=1, clock=RealtimeClock(4.0)),
        on_first_key=keys.append,
    )
    ws_url = "/api/v1/ws?vehicles=SIM-001"
    with heap_frozen(), TestClient(app) as client:
        r = client.post("/api/v1/session", json={"key": keys[0]})
        assert r.status_code == 201, r.text
        csrf = r.json()["csrf_token"]
        cookie = {"Cookie": f"{COOKIE}={r.cookies[COOKIE]}"}
        client.cookies.clear()  # each connection below says what it carries
        # Another site's page rides on the cookie: refused.
        with client.websocket_connect(
            ws_url, headers={**cookie, "Origin": "http://evil.example"}
        ) as ws:
            assert _recv(ws)["type"] == "error"
            with pytest.raises(WebSocketDisconnect) as closed:
                _recv(ws)
            assert closed.value.code == 4401
        # No credentials at all, then the key as the first message.
        with client.websocket_connect(ws_url) as ws:
            ws.send_json({"type": "auth", "key": keys[0]})
            assert _recv(ws)["type"] == "snapshot"
        # The gateway's own page: the cookie is enough; logging out closes the socket.
        with client.websocket_connect(
            ws_url, headers={**cookie, "Origin": "http://testserver"}
        ) as ws:
            assert _recv(ws)["type"] == "snapshot"
            r = client.delete("/api/v1/session", headers={**cookie, "X-CSRF-Token": csrf})
            assert r.status_code == 204
            with pytest.raises(WebSocketDisconnect) as closed:
                for _ in range(10_000):  # live events until the close (each wait bounded)
                    msg = _recv(ws, timeout=15)
                    if msg["type"] == "error":
                        assert "session ended" in msg["reason"]
            assert closed.value.code == 4401
