"""The dashboard's login in a real browser (Debian's chromium, Playwright): a login link
carries a one-time code, never a key, and leaves nothing usable in the address, the browser's
history, its storage, its websocket URL or its Referer headers; the session cookie is HttpOnly
and SameSite=Strict; logout ends the session on the server; a link on another site cannot log
anyone in (login CSRF); the page runs under its Content-Security-Policy without a violation."""

from __future__ import annotations

import contextlib
import http.server
import sqlite3
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from tests import test_dashboard as dash
from tests.support import web
from tests.test_dashboard import CHROMIUM, CHROMIUM_ARGS, LONG, Gateway, expect

# The dashboard tests' fixtures: a gateway with a simulated fleet, chromium, a fresh page.
gateway = dash.gateway
browser = dash.browser
page = dash.page

pytestmark = pytest.mark.browser


def _history(profile: Path) -> list[str]:
    """Every address in the Chromium profile's history (read after the browser closed)."""
    with sqlite3.connect(profile / "Default" / "History") as db:
        return [row[0] for row in db.execute("SELECT url FROM urls")]


def test_login_link_leaves_nothing_usable_in_the_browser(
    browser: Any, gateway: Gateway, tmp_path: Path
) -> None:
    key = gateway.key("operator")
    code = gateway.login_code(key)
    profile = tmp_path / "profile"
    context = browser.browser_type.launch_persistent_context(
        str(profile), executable_path=CHROMIUM, args=CHROMIUM_ARGS
    )
    try:
        page = context.new_page()
        ws_urls: list[str] = []
        requests: list[Any] = []
        violations: list[str] = []
        errors: list[str] = []
        page.on("websocket", lambda ws: ws_urls.append(ws.url))
        page.on("request", lambda r: requests.append(r))
        page.on("pageerror", lambda exc: errors.append(str(exc)))
        page.on(
            "console",
            lambda m: violations.append(m.text) if "Content Security Policy" in m.text else None,
        )

        page.goto(f"{gateway.base}/#login={code}")
        # The page says whose key the link logs in as, and waits to be asked.
        expect(page.locator("#code-name")).to_have_text("operator (browser test)", timeout=LONG)
        assert "login=" not in page.url and code not in page.url, page.url
        assert not [c for c in context.cookies() if c["name"] == "eqgw_session"]
        page.get_by_role("button", name="Sign in").click()
        expect(page.locator("#conn")).to_have_attribute("data-state", "live", timeout=LONG)
        page.goto(f"{gateway.base}/#/vehicle/SIM-001")
        expect(page.locator(".unit-panel").first).to_be_visible(timeout=LONG)
        assert page.url.endswith("#/vehicle/SIM-001"), page.url

        storage = page.evaluate(
            "JSON.stringify([Object.entries(localStorage), Object.entries(sessionStorage)])"
        )
        assert key not in storage and code not in storage, storage
        assert "eqgw_session" not in page.evaluate("document.cookie")  # HttpOnly
        (cookie,) = [c for c in context.cookies() if c["name"] == "eqgw_session"]
        assert cookie["httpOnly"] is True and cookie["sameSite"] == "Strict", cookie
        assert key not in cookie["value"] and code not in cookie["value"]

        # The websocket is authenticated by the cookie: no key in its URL, and it is live.
        assert ws_urls and all("key" not in u for u in ws_urls), ws_urls
        # The code is in no request's address and no Referer (a fragment is never sent);
        # the key in none at all; the page's own files are fetched without a Referer.
        for r in requests:
            for text in (r.url, r.headers.get("referer") or ""):
                assert key not in text and code not in text, (r.url, r.all_headers())
        static = [r for r in requests if "/static/" in r.url]
        assert static and all("referer" not in r.all_headers() for r in static)

        # The link was used up: the same code logs no one in again, anywhere.
        again = web.post(f"{gateway.base}/api/v1/session", json={"code": code})
        assert again.status_code == 401, again.text

        # Logout ends the session on the server: the cookie is refused afterwards.
        page.get_by_role("button", name="Log out").click()
        expect(page.get_by_label("API key")).to_be_visible(timeout=LONG)
        r = web.get(
            f"{gateway.base}/api/v1/session",
            headers={"Cookie": f"eqgw_session={cookie['value']}"},
        )
        assert r.status_code == 401, r.text
        assert not violations, violations
        assert not errors, errors
    finally:
        context.close()
    # What the browser's history kept: never the key; a login link at most, used up.
    urls = _history(profile)
    assert urls and not any(key in u for u in urls), urls
    for u in urls:
        if "login=" in u:
            kept = u.split("login=", 1)[1]
            r = web.post(f"{gateway.base}/api/v1/session", json={"code": kept})
            assert r.status_code == 401, (u, r.text)


@contextlib.contextmanager
def _attacker_site(links: dict[str, str]) -> Iterator[str]:
    """Another site: a real HTTP server on `localhost` (another site than `127.0.0.1`, where
    the gateway is) whose page links to the gateway; its address."""
    html = "".join(f'<p><a id="{n}" href="{href}">{n}</a></p>' for n, href in links.items())
    body = f"<!doctype html><title>elsewhere</title>{html}".encode()

    class Page(http.server.BaseHTTPRequestHandler):
        def do_GET(self) -> None:
            self.send_response(200)
            self.send_header("Content-Type", "text/html")
            self.send_header("Content-Length", str(len(body)))
            self.end_headers()
            self.wfile.write(body)

        def log_message(self, *_args: Any) -> None:
            pass

    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Page)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        yield f"http://localhost:{server.server_address[1]}/"
    finally:
        server.shutdown()
        server.server_close()


def test_a_link_on_another_site_logs_no_one_in(page: Any, gateway: Gateway) -> None:
    """Login CSRF: another site links to the dashboard with its own key, or with a login
    link of its own key. The key logs no one in; the code is shown for what it is and used
    only if the person asks; the depot manager's session stays theirs."""
    r = web.post(
        f"{gateway.base}/api/v1/keys",
        json={"name": "attacker", "role": "viewer"},
        headers={"Authorization": f"Bearer {gateway.admin}"},
    )
    assert r.status_code == 201, r.text
    attacker = r.json()["key"]
    code = gateway.login_code(attacker)
    links = {
        "by-key": f"{gateway.base}/?key={attacker}",
        "by-code": f"{gateway.base}/#login={code}",
    }

    with _attacker_site(links) as elsewhere:
        _login_csrf(page, gateway, elsewhere, attacker, code)


def _login_csrf(page: Any, gateway: Gateway, elsewhere: str, attacker: str, code: str) -> None:
    # Not logged in: the link with a key shows the login form, and sets no session.
    page.goto(elsewhere)
    page.click("#by-key")
    expect(page.get_by_label("API key")).to_be_visible(timeout=LONG)
    assert attacker not in page.url
    assert not [c for c in page.context.cookies() if c["name"] == "eqgw_session"]

    # The depot manager logs in (the form), then follows the other site's links.
    page.get_by_label("API key").fill(gateway.key("operator"))
    page.get_by_role("button", name="Log in").click()
    expect(page.locator("#who")).to_contain_text("operator", timeout=LONG)
    page.goto(elsewhere)
    page.click("#by-key")
    expect(page.locator("#who")).to_contain_text("operator (browser test)", timeout=LONG)
    expect(page.locator("#conn")).to_have_attribute("data-state", "live", timeout=LONG)
    assert attacker not in page.url

    page.goto(elsewhere)
    page.click("#by-code")
    expect(page.locator("#code-name")).to_have_text("attacker", timeout=LONG)
    assert "login=" not in page.url
    page.get_by_role("button", name="Cancel").click()
    expect(page.locator("#who")).to_contain_text("operator (browser test)", timeout=LONG)
    me = page.request.get(f"{gateway.base}/api/v1/session")
    assert me.ok and me.json()["name"] == "operator (browser test)", me.text()

    # The other site's own page cannot use the code either: its login request is refused
    # (403, before its body is read), and the refused attempt did not use the code up.
    page.goto(elsewhere)
    with page.expect_response(f"{gateway.base}/api/v1/session") as refused:
        page.evaluate(
            """([base, code]) => fetch(base + "/api/v1/session", {method: "POST",
                mode: "no-cors", credentials: "include", body: JSON.stringify({code})})
                .catch(() => null)""",
            [gateway.base, code],
        )
    assert refused.value.status == 403, refused.value.status
    me = page.request.get(f"{gateway.base}/api/v1/session")
    assert me.ok and me.json()["name"] == "operator (browser test)", me.text()
    r = web.post(f"{gateway.base}/api/v1/session/code", json={"code": code})
    assert r.status_code == 200, r.text
