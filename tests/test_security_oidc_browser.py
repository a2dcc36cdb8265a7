"""Single sign-on in a real browser (Debian's chromium, Playwright) against the real OpenID
provider (tests/oidc/provider.js): the login page's "Sign in with SSO", the provider's login
form, and back on the dashboard as the person, with their depot's vehicles only; the gateway
and the provider on different sites (localhost, 127.0.0.1), as a provider elsewhere is, so
the cookies are tried across a cross-site redirect; logout; no Content-Security-Policy
violation on the gateway's pages."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import pytest

from tests import test_dashboard as dash
from tests.oidc_helpers import SECRET, running_provider
from tests.proc_helpers import free_port
from tests.support import web
from tests.test_dashboard import LONG, Gateway, expect, run_gateway
from tests.test_security_oidc import DEPOTS, GROUPS, USERS

browser = dash.browser

pytestmark = pytest.mark.browser


@pytest.fixture(scope="module")
def sso_gateway(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Gateway]:
    """A gateway with single sign-on at the provider, reached at http://localhost:PORT."""
    port = free_port()
    callback = f"http://localhost:{port}/auth/oidc/callback"
    log = tmp_path_factory.mktemp("oidc") / "provider.log"
    with running_provider(USERS, [callback], log=log) as issuer:
        config: dict[str, Any] = {
            "vehicles": [{"id": v, "depot": d} for v, d in DEPOTS.items()],
            "oidc": {
                "issuer": issuer,
                "client_id": "eqgw",
                "client_secret": SECRET,
                "scopes": "openid email profile groups",
                "groups": GROUPS,
                "redirect_url": callback,
            },
        }
        with run_gateway(tmp_path_factory, len(DEPOTS), config=config, port=port) as gw:
            gw.base = f"http://localhost:{port}"
            yield gw


def test_sign_in_with_sso_from_the_login_page(browser: Any, sso_gateway: Gateway) -> None:
    base = sso_gateway.base
    context = browser.new_context(viewport={"width": 1280, "height": 900})
    try:
        page = context.new_page()
        violations: list[str] = []
        errors: list[str] = []
        page.on("pageerror", lambda exc: errors.append(str(exc)))
        page.on(
            "console",
            lambda m: (
                violations.append(m.text)
                if "Content Security Policy" in m.text
                and m.location.get("url", "").startswith(base)
                else None
            ),
        )
        page.goto(f"{base}/")
        page.get_by_role("link", name="Sign in with SSO").click()
        # The provider's own login form (oidc-provider's devInteractions).
        page.locator('input[name="login"]').fill("nora")
        page.locator('input[name="password"]').fill("any password")
        page.get_by_role("button", name="Sign-in").click()

        who = "nora@depot.example (SSO) · operator"
        expect(page.locator("#who")).to_have_text(who, timeout=LONG)
        expect(page.locator("#conn")).to_have_attribute("data-state", "live", timeout=LONG)
        assert page.url == f"{base}/", page.url
        # North's vehicles only.
        expect(page.locator('a[href="#/vehicle/SIM-001"]').first).to_be_visible(timeout=LONG)
        expect(page.locator('a[href="#/vehicle/SIM-002"]').first).to_be_visible()
        assert page.locator('a[href="#/vehicle/SIM-003"]').count() == 0

        cookies = {c["name"]: c for c in context.cookies()}
        session = cookies["eqgw_session"]
        assert session["httpOnly"] and session["sameSite"] == "Strict", session
        assert "eqgw_oidc" not in cookies, cookies  # the sign-in's secrets are gone

        page.get_by_role("button", name="Log out").click()
        expect(page.get_by_label("API key")).to_be_visible(timeout=LONG)
        r = web.get(
            f"{base}/api/v1/session", headers={"Cookie": f"eqgw_session={session['value']}"}
        )
        assert r.status_code == 401, r.text
        assert not violations, violations
        assert not errors, errors
    finally:
        context.close()


def test_a_user_in_no_mapped_group_sees_why(browser: Any, sso_gateway: Gateway) -> None:
    context = browser.new_context()
    try:
        page = context.new_page()
        page.goto(f"{sso_gateway.base}/")
        page.get_by_role("link", name="Sign in with SSO").click()
        page.locator('input[name="login"]').fill("otto")
        page.locator('input[name="password"]').fill("any password")
        page.get_by_role("button", name="Sign-in").click()
        expect(page.get_by_role("heading", name="No access to this gateway")).to_be_visible(
            timeout=LONG
        )
        expect(page.get_by_role("alert")).to_contain_text("none of your groups (canteen, staff)")
        page.get_by_role("link", name="Back to the login page").click()
        expect(page.get_by_label("API key")).to_be_visible(timeout=LONG)
        assert not [c for c in context.cookies() if c["name"] == "eqgw_session"]
    finally:
        context.close()


def test_a_person_operating_one_depot_sees_controls_there_only(
    browser: Any, sso_gateway: Gateway
) -> None:
    """Max is an operator of North and a viewer of South: the vehicle page offers the controls
    on North's vehicles and not on South's (where the server would refuse them)."""
    context = browser.new_context(viewport={"width": 1280, "height": 900})
    try:
        page = context.new_page()
        errors: list[str] = []
        page.on("pageerror", lambda exc: errors.append(str(exc)))
        page.goto(f"{sso_gateway.base}/")
        page.get_by_role("link", name="Sign in with SSO").click()
        page.locator('input[name="login"]').fill("max")
        page.locator('input[name="password"]').fill("any password")
        page.get_by_role("button", name="Sign-in").click()
        expect(page.locator("#who")).to_have_text(
            "max@depot.example (SSO) · operator", timeout=LONG
        )
        expect(page.locator('a[href="#/vehicle/SIM-003"]').first).to_be_visible(timeout=LONG)

        page.goto(f"{sso_gateway.base}/#/vehicle/SIM-001")
        panel = page.locator(".unit-panel").first
        expect(panel).to_be_visible(timeout=LONG)
        expect(panel.get_by_role("heading", name="Controls")).to_be_visible(timeout=LONG)

        page.goto(f"{sso_gateway.base}/#/vehicle/SIM-003")
        panel = page.locator(".unit-panel").first
        expect(page.locator("#v-title")).to_have_text("SIM-003", timeout=LONG)
        expect(panel).to_be_visible(timeout=LONG)
        expect(panel.locator(".live")).not_to_be_empty(timeout=LONG)
        assert page.locator(".unit-panel").get_by_role("heading", name="Controls").count() == 0
        # And a reload straight onto South's page (the fleet not loaded first) shows none either.
        page.reload()
        expect(page.locator(".unit-panel").first).to_be_visible(timeout=LONG)
        expect(page.locator(".unit-panel .live").first).not_to_be_empty(timeout=LONG)
        assert page.locator(".unit-panel").get_by_role("heading", name="Controls").count() == 0
        assert not errors, errors
    finally:
        context.close()
