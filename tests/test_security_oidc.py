"""Single sign-on against a real OpenID provider on loopback (panva/oidc-provider, OpenID
Certified; tests/oidc/provider.js): the browser's part driven by httpx following the redirects
and posting the provider's login form, on SQLite and PostgreSQL.

A good sign-in gets a session (cookie, CSRF, logout, revocation) with the role and depots its
groups map to, and reads only those depots' vehicles; a person of several groups holds the
strongest role per depot; the audit log names the person. Refused, each with a page saying
why: a user in no mapped group, an ID token for another audience, one expired, one signed by a
key the provider does not publish, an answer whose state differs from the browser's, one
whose ID token carries another nonce, a callback opened in another browser. The bad tokens are
made by the provider itself (its clients eqgw-wrong-aud, eqgw-expired, eqgw-foreign-key) and
reach the gateway through its real callback.
"""

from __future__ import annotations

import asyncio
import html
import re
from collections.abc import AsyncIterator, Callable, Iterator
from contextlib import asynccontextmanager
from pathlib import Path
from typing import Any
from urllib.parse import parse_qsl, urlencode, urljoin, urlsplit, urlunsplit

import httpx
import pytest

from eqgw.config import OidcSettings, VehicleConfig
from tests.api_helpers import Served, served
from tests.oidc_helpers import SECRET, running_provider
from tests.proc_helpers import free_port

GATEWAY = "http://test"
CALLBACK = f"{GATEWAY}/auth/oidc/callback"
DEPOTS = {"SIM-001": "north", "SIM-002": "north", "SIM-003": "south"}
NORTH = {"SIM-001", "SIM-002"}
USERS = {
    "nora": {
        "email": "nora@depot.example",
        "name": "Nora North",
        "groups": ["eqgw-north-operators", "staff"],
    },
    "max": {
        "email": "max@depot.example",
        "name": "Max Mixed",
        "groups": ["eqgw-north-operators", "eqgw-south-viewers"],
    },
    "otto": {"email": "otto@depot.example", "name": "Otto Outside", "groups": ["staff", "canteen"]},
}
GROUPS = {
    "eqgw-north-operators": {"role": "operator", "depots": ["north"]},
    "eqgw-south-viewers": {"role": "viewer", "depots": ["south"]},
    "eqgw-admins": {"role": "admin", "all": True},
}
CONTROL = {"all_units": True, "jump_start_override": True, "expires_in_s": 5}


@pytest.fixture(scope="module")
def issuer(tmp_path_factory: pytest.TempPathFactory) -> Iterator[str]:
    """The provider most tests sign in at: claims in the ID token, as Keycloak, Entra ID or
    Okta put a groups claim there."""
    log = tmp_path_factory.mktemp("oidc") / "provider.log"
    with running_provider(USERS, [CALLBACK], log=log) as url:
        yield url


@asynccontextmanager
async def gateway(
    db_url: str, issuer: str, client_id: str = "eqgw", **oidc: Any
) -> AsyncIterator[Served]:
    """A gateway with three simulated vehicles in two depots and single sign-on at `issuer`."""
    config = {
        "vehicles": [VehicleConfig(id=v, depot=d) for v, d in DEPOTS.items()],
        "oidc": OidcSettings(
            issuer=issuer,
            client_id=client_id,
            client_secret=SECRET,
            scopes="openid email profile groups",
            groups=GROUPS,  # type: ignore[arg-type]
            **oidc,
        ),
    }
    async with served(db_url, config=config, public_url=GATEWAY) as s:
        yield s


def browser(s: Served) -> httpx.AsyncClient:
    """A browser of its own (its own cookies): the gateway in process, the provider over
    loopback."""
    return httpx.AsyncClient(
        mounts={f"{GATEWAY}": httpx.ASGITransport(app=s.app)}, base_url=GATEWAY, timeout=30
    )


async def to_callback(client: httpx.AsyncClient, login: str) -> str:
    """Start a sign-in and go through the provider (its login form as `login`, any password)
    up to the address it sends the browser back to, which is returned unopened."""
    r = await client.get("/auth/oidc/login")
    for _ in range(20):
        if r.is_redirect:
            target = urljoin(str(r.url), r.headers["location"])
            if target.startswith(CALLBACK):
                return target
            r = await client.get(target)
            continue
        assert r.status_code == 200, (r.status_code, r.url, r.text[:500])
        action = re.search(r'<form[^>]*action="([^"]+)"', r.text)
        assert action, r.text[:1000]
        form = {"prompt": "login", "login": login, "password": "anything"}
        r = await client.post(urljoin(str(r.url), html.unescape(action[1])), data=form)
    raise AssertionError("the provider never sent the browser back")


async def sign_in(
    client: httpx.AsyncClient, login: str, tamper: Callable[[str], str] = lambda url: url
) -> httpx.Response:
    """The gateway's answer to the provider's callback (a redirect to the dashboard with the
    session cookie, or a refusal page); `tamper` may change the callback address first."""
    return await client.get(tamper(await to_callback(client, login)))


def with_query(url: str, **changes: str) -> str:
    parts = urlsplit(url)
    query = dict(parse_qsl(parts.query))
    query.update(changes)
    return urlunsplit(parts._replace(query=urlencode(query)))


async def audit(s: Served, action: str) -> list[dict[str, Any]]:
    r = await s.client.get("/api/v1/audit", params={"limit": 1000}, headers=s.auth())
    assert r.status_code == 200, r.text
    return [e for e in r.json()["entries"] if e["action"] == action]


def refusal(r: httpx.Response) -> str:
    """The text of a refusal page (its one alert paragraph), unescaped."""
    found = re.search(r'<p class="error" role="alert">(.*?)</p>', r.text, re.S)
    assert found, r.text
    return html.unescape(found[1])


def session_cookie(r: httpx.Response) -> str | None:
    for k, v in r.headers.multi_items():
        if k == "set-cookie" and v.startswith("eqgw_session="):
            return v.lower()
    return None


async def test_sign_in_maps_groups_to_a_scoped_session_audited_by_person(
    db_url: str, issuer: str
) -> None:
    async with gateway(db_url, issuer, session_max_age_s=3600) as s, browser(s) as b:
        r = await sign_in(b, "nora")
        assert r.status_code == 303 and r.headers["location"] == "/", (r.status_code, r.text)
        cookie = session_cookie(r)
        assert cookie is not None, r.headers
        assert "httponly" in cookie and "samesite=strict" in cookie and "max-age=3600" in cookie
        assert "eqgw_oidc=" in r.headers.get("set-cookie", "")  # the sign-in's cookie dropped

        me = (await b.get("/api/v1/session")).json()
        assert me["role"] == "operator", me
        assert me["scope"] == {"groups": ["north"], "vehicles": []}, me
        assert me["person"] == {"subject": "nora", "email": "nora@depot.example"}, me
        assert me["name"] == "nora@depot.example (SSO)", me
        csrf = me["csrf_token"]

        # Only North's vehicles; South's is as unknown as one that does not exist.
        listed = (await b.get("/api/v1/vehicles")).json()["vehicles"]
        assert {v["id"] for v in listed} == NORTH, listed
        assert (await b.get("/api/v1/vehicles/SIM-003/live")).status_code == 404
        # An operator's write by cookie: with the CSRF token only.
        cmd = "/api/v1/vehicles/SIM-001/commands"
        assert (await b.post(cmd, json=CONTROL)).status_code == 403
        r = await b.post(cmd, json=CONTROL, headers={"X-CSRF-Token": csrf})
        assert r.status_code == 202, r.text
        r = await b.post(
            "/api/v1/vehicles/SIM-003/commands", json=CONTROL, headers={"X-CSRF-Token": csrf}
        )
        assert r.status_code == 404, r.text
        # Keys stay for machines: the admin's key lists the person's row, without a key.
        keys = (await s.client.get("/api/v1/keys", headers=s.auth())).json()
        (row,) = [k for k in keys if k["prefix"] == "sso"]
        assert row["name"] == "nora@depot.example (SSO)" and row["role"] == "operator", row

        # The audit log names the person: the sign-in, the command, the logout.
        (entry,) = await audit(s, "session.sso")
        assert entry["outcome"] == "accepted", entry
        assert (entry["subject"], entry["email"]) == ("nora", "nora@depot.example"), entry
        assert entry["key_id"] == row["id"] and entry["detail"] == "operator of depots north"
        commands = [e for e in await audit(s, "command.control") if e["outcome"] == "accepted"]
        assert commands and all(e["subject"] == "nora" for e in commands), commands
        assert commands[0]["email"] == "nora@depot.example", commands

        assert (await b.delete("/api/v1/session")).status_code == 403  # without the CSRF token
        r = await b.delete("/api/v1/session", headers={"X-CSRF-Token": csrf})
        assert r.status_code == 204, r.text
        assert (await b.get("/api/v1/session")).status_code == 401
        (out,) = await audit(s, "session.logout")
        assert (out["subject"], out["email"], out["key_id"]) == ("nora", entry["email"], row["id"])


async def test_several_groups_hold_the_strongest_role_per_depot(db_url: str, issuer: str) -> None:
    async with gateway(db_url, issuer) as s, browser(s) as b:
        assert (await sign_in(b, "max")).status_code == 303
        me = (await b.get("/api/v1/session")).json()
        # The strongest role and every depot, and what each group gives.
        assert me["role"] == "operator", me
        assert me["scope"] == {"groups": ["north", "south"], "vehicles": []}, me
        assert me["grants"] == [
            {"role": "operator", "scope": {"groups": ["north"], "vehicles": []}},
            {"role": "viewer", "scope": {"groups": ["south"], "vehicles": []}},
        ], me
        headers = {"X-CSRF-Token": me["csrf_token"]}
        listed = (await b.get("/api/v1/vehicles")).json()["vehicles"]
        assert {v["id"] for v in listed} == set(DEPOTS), listed
        r = await b.post("/api/v1/vehicles/SIM-001/commands", json=CONTROL, headers=headers)
        assert r.status_code == 202, r.text
        # South sees the vehicle but is a viewer there: refused, saying so.
        r = await b.post("/api/v1/vehicles/SIM-003/commands", json=CONTROL, headers=headers)
        assert r.status_code == 403, r.text
        assert r.json()["detail"] == "you are viewer of vehicle SIM-003; this needs operator"


async def test_a_user_in_no_mapped_group_is_refused_with_a_page(db_url: str, issuer: str) -> None:
    async with gateway(db_url, issuer) as s, browser(s) as b:
        r = await sign_in(b, "otto")
        assert r.status_code == 403, r.text
        assert r.headers["content-type"].startswith("text/html")
        assert "No access to this gateway" in r.text
        assert refusal(r) == (
            "You signed in as otto@depot.example, but none of your groups (canteen, staff) "
            "gives access to this gateway. Ask the administrator of the identity provider "
            "to add you to a group that does."
        )
        assert session_cookie(r) is None
        assert (await b.get("/api/v1/session")).status_code == 401
        # Refused, and the log says who was.
        (entry,) = await audit(s, "session.sso")
        assert entry["outcome"] == "refused" and entry["status_code"] == 403, entry
        assert (entry["subject"], entry["email"], entry["key_id"]) == (
            "otto",
            "otto@depot.example",
            None,
        )
        keys = (await s.client.get("/api/v1/keys", headers=s.auth())).json()
        assert not [k for k in keys if k["prefix"] == "sso"], keys


@pytest.mark.parametrize(
    ("client_id", "says"),
    [
        (
            "eqgw-wrong-aud",
            "The ID token is meant for 'someone-else', not for this gateway "
            "(oidc.client_id 'eqgw-wrong-aud').",
        ),
        ("eqgw-expired", "The ID token had expired 3"),
        (
            "eqgw-foreign-key",
            "The ID token's signature does not verify with the keys the identity provider "
            "publishes: it was not signed by the provider, or was altered on the way.",
        ),
    ],
    ids=["wrong-audience", "expired", "bad-signature"],
)
async def test_bad_id_tokens_are_refused(
    sqlite_url: str, issuer: str, client_id: str, says: str
) -> None:
    async with gateway(sqlite_url, issuer, client_id=client_id) as s, browser(s) as b:
        r = await sign_in(b, "nora")
        assert r.status_code == 401, r.text
        assert "Sign-in refused" in r.text
        assert refusal(r).startswith(says), refusal(r)
        assert session_cookie(r) is None
        assert (await b.get("/api/v1/session")).status_code == 401


async def test_state_nonce_and_browser_must_be_this_sign_ins(sqlite_url: str, issuer: str) -> None:
    async with gateway(sqlite_url, issuer) as s:
        # An answer with another state (a forged or mixed-up callback).
        async with browser(s) as b:
            r = await sign_in(b, "nora", lambda url: with_query(url, state="forged"))
            assert r.status_code == 400, r.text
            assert "its state differs" in refusal(r)
            assert session_cookie(r) is None
        # A callback address opened in another browser (login CSRF): no sign-in cookie there.
        async with browser(s) as b, browser(s) as victim:
            url = await to_callback(b, "nora")
            r = await victim.get(url)
            assert r.status_code == 400, r.text
            assert "was not started in this browser" in refusal(r)
            assert (await victim.get("/api/v1/session")).status_code == 401
            # The code was not spent: the browser that started the sign-in completes it.
            assert (await b.get(url)).status_code == 303
        # The browser's nonce differs from the one in the ID token.
        async with browser(s) as b:
            url = await to_callback(b, "nora")
            state, _nonce, verifier = b.cookies["eqgw_oidc"].split(".")
            b.cookies.set("eqgw_oidc", f"{state}.other-nonce.{verifier}", path="/auth/oidc/")
            r = await b.get(url)
            assert r.status_code == 401, r.text
            assert "its nonce differs" in refusal(r)
        # The provider's own refusal (the person cancelled) is passed on.
        async with browser(s) as b:
            url = with_query(CALLBACK, error="access_denied", error_description="cancelled")
            r = await b.get(url)
            assert r.status_code == 403 and "(access_denied: cancelled)" in refusal(r)
        # Nobody to name: counted, as requests without a key are (written at the next flush).
        await asyncio.to_thread(s.rt.audit_log.refusals.flush, s.rt.engine)
        entries = await audit(s, "session.sso")
        counted = {e["status_code"]: e["request"]["count"] for e in entries if e["key_id"] is None}
        assert counted == {400: 2, 401: 1, 403: 1}, counted


async def test_revoking_the_person_ends_their_sessions_and_a_new_sign_in_starts_afresh(
    sqlite_url: str, issuer: str
) -> None:
    async with gateway(sqlite_url, issuer) as s, browser(s) as b:
        assert (await sign_in(b, "nora")).status_code == 303
        keys = (await s.client.get("/api/v1/keys", headers=s.auth())).json()
        (row,) = [k for k in keys if k["prefix"] == "sso"]
        # A person's row has no key: it cannot be rotated into one, nor log in by a link.
        r = await s.client.post(
            f"/api/v1/keys/{row['id']}/rotate", json={"overlap_s": 60}, headers=s.auth()
        )
        assert r.status_code == 422 and "single sign-on" in r.json()["detail"], r.text
        r = await s.client.delete(f"/api/v1/keys/{row['id']}", headers=s.auth())
        assert r.status_code == 200, r.text
        assert (await b.get("/api/v1/session")).status_code == 401
        # Still in the group at the provider: signing in again works, as a new key row.
        assert (await sign_in(b, "nora")).status_code == 303
        me = (await b.get("/api/v1/session")).json()
        assert me["key_id"] != row["id"] and me["person"]["subject"] == "nora", me


async def test_groups_from_userinfo_when_the_id_token_has_none(
    sqlite_url: str, tmp_path: Path
) -> None:
    # The specification's default: claims asked for by scope come from UserInfo only.
    with running_provider(USERS, [CALLBACK], conform=True, log=tmp_path / "p.log") as url:
        async with gateway(sqlite_url, url) as s, browser(s) as b:
            assert (await sign_in(b, "max")).status_code == 303
            me = (await b.get("/api/v1/session")).json()
            assert me["role"] == "operator" and len(me["grants"]) == 2, me
            assert me["person"]["email"] == "max@depot.example", me


async def test_a_provider_that_does_not_answer_is_a_page_not_a_hang(sqlite_url: str) -> None:
    async with gateway(sqlite_url, f"http://127.0.0.1:{free_port()}", timeout_s=2) as s:
        r = await s.client.get("/auth/oidc/login")
        assert r.status_code == 502, r.text
        assert "The identity provider cannot be reached" in r.text
        assert "/.well-known/openid-configuration does not answer" in refusal(r)


async def test_without_single_sign_on_its_routes_answer_404(sqlite_url: str) -> None:
    async with served(sqlite_url, vehicles=1) as s:
        assert (await s.client.get("/auth/oidc")).status_code == 404
        r = await s.client.get("/auth/oidc/login")
        assert r.status_code == 404 and "log in with an API key" in refusal(r)


async def test_the_login_page_is_told_how_to_offer_it(sqlite_url: str, issuer: str) -> None:
    async with gateway(sqlite_url, issuer, label="Sign in with Depot ID") as s:
        r = await s.client.get("/auth/oidc")
        assert r.json() == {"login_url": "/auth/oidc/login", "label": "Sign in with Depot ID"}
        # The sign-in starts with PKCE (S256), a state and a nonce, at the provider.
        r = await s.client.get("/auth/oidc/login")
        assert r.status_code == 303, r.text
        target = urlsplit(r.headers["location"])
        query = dict(parse_qsl(target.query))
        assert f"{target.scheme}://{target.netloc}" == issuer
        assert query["code_challenge_method"] == "S256" and len(query["code_challenge"]) == 43
        assert query["redirect_uri"] == CALLBACK and query["response_type"] == "code"
        assert query["state"] and query["nonce"] and query["client_id"] == "eqgw"
        cookie = r.headers["set-cookie"].lower()
        assert cookie.startswith("eqgw_oidc=") and "httponly" in cookie, cookie
        assert "samesite=lax" in cookie and "path=/auth/oidc/" in cookie, cookie


@pytest.mark.parametrize(
    ("settings", "error"),
    [
        ({"issuer": "http://login.example.com"}, "must be an https URL"),
        ({"issuer": "https://login.example.com", "groups": {}}, "oidc.client_id is required"),
        ({"client_id": "eqgw", "groups": {}}, "maps no group"),
        (
            {
                "client_id": "eqgw",
                "groups": {"g": {"role": "viewer", "all": True, "depots": ["n"]}},
            },
            "either `all = true`",
        ),
        ({"client_id": "eqgw", "groups": {"g": {"role": "viewer"}}}, "either `all = true`"),
        ({"client_id": "eqgw", "scopes": "email", "groups": GROUPS}, "must include openid"),
    ],
)
def test_settings_refuse_what_cannot_work(settings: dict[str, Any], error: str) -> None:
    values = {"issuer": "https://login.example.com", **settings}
    with pytest.raises(ValueError, match=re.escape(error)):
        OidcSettings(**values)
