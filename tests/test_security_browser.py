"""The dashboard's login in a real browser (Debian's chromium, Playwright): the key leaves the
address, the page's storage, its websocket URL and its Referer headers; the session cookie is
HttpOnly and SameSite=Strict; logout ends the session on the server; the page runs under its
Content-Security-Policy without a violation."""

from __future__ import annotations

from typing import Any

import httpx
import pytest

from tests import test_dashboard as dash
from tests.test_dashboard import LONG, Gateway, expect, login_by_url

# The dashboard tests' fixtures: a gateway with a simulated fleet, chromium, a fresh page.
gateway = dash.gateway
browser = dash.browser
page = dash.page

pytestmark = pytest.mark.browser


def test_login_link_leaves_no_key_in_the_browser(page: Any, gateway: Gateway) -> None:
    key = gateway.key("operator")
    ws_urls: list[str] = []
    requests: list[Any] = []
    violations: list[str] = []
    page.on("websocket", lambda ws: ws_urls.append(ws.url))
    page.on("request", lambda r: requests.append(r))
    page.on(
        "console",
        lambda m: violations.append(m.text) if "Content Security Policy" in m.text else None,
    )

    login_by_url(page, gateway, key, "#/vehicle/SIM-001")  # waits for the live websocket
    expect(page.locator(".unit-panel").first).to_be_visible(timeout=LONG)

    assert key not in page.url and "key=" not in page.url, page.url
    assert page.url.endswith("#/vehicle/SIM-001"), page.url
    storage = page.evaluate(
        "JSON.stringify([Object.entries(localStorage), Object.entries(sessionStorage)])"
    )
    assert key not in storage, storage
    assert "eqgw_session" not in page.evaluate("document.cookie")  # HttpOnly: not for scripts
    (cookie,) = [c for c in page.context.cookies() if c["name"] == "eqgw_session"]
    assert cookie["httpOnly"] is True and cookie["sameSite"] == "Strict", cookie
    assert key not in cookie["value"]

    # The websocket is authenticated by the cookie: no key in its URL, and it is live.
    assert ws_urls and all("key" not in u for u in ws_urls), ws_urls
    expect(page.locator("#conn")).to_have_attribute("data-state", "live", timeout=LONG)
    # Only the link itself carries the key (answered by a redirect); no other request does,
    # and the page's own files are fetched without a Referer.
    first, *rest = requests
    assert key in first.url and first.response() is not None
    assert first.response().status == 303
    for r in rest:
        assert key not in r.url and key not in (r.headers.get("referer") or ""), r.url
    static = [r for r in requests if "/static/" in r.url]
    assert static and all("referer" not in r.all_headers() for r in static), [
        r.all_headers().get("referer") for r in static
    ]

    # Logout ends the session on the server: the cookie is refused afterwards.
    page.get_by_role("button", name="Log out").click()
    expect(page.get_by_label("API key")).to_be_visible(timeout=LONG)
    r = httpx.get(
        f"{gateway.base}/api/v1/session", headers={"Cookie": f"eqgw_session={cookie['value']}"}
    )
    assert r.status_code == 401, r.text
    assert not violations, violations
