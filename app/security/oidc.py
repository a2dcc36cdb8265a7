"""Single sign-on for the dashboard: OpenID Connect, the authorization code flow with PKCE.

1. `GET /auth/oidc/login` (the login page's "Sign in with SSO") sends the browser to the
   provider's authorization endpoint with a fresh `state`, `nonce` and PKCE challenge (S256).
   The three secrets stay in the browser, in a cookie of their own (`eqgw_oidc`: HttpOnly,
   SameSite=Lax because the provider's redirect back is a cross-site navigation, which a
   Strict cookie would miss; 10 minutes; path /auth/oidc/). Nothing is stored on the gateway,
   so the callback may reach any gateway of the database; a callback address made in another
   browser finds no such cookie there and logs no one in.
2. The provider authenticates the person and sends the browser to `GET /auth/oidc/callback`
   with a code. The state must equal the cookie's; the code is exchanged at the token endpoint
   with the PKCE verifier (and the client secret); the ID token is checked by authlib's
   `CodeIDToken` over joserfc (authlib's JOSE library), not by code of ours: its signature
   against the keys the provider publishes (asymmetric algorithms only), issuer, audience
   (this client), authorized party, expiry and issue time (within `clock_skew_s`), the nonce
   of the cookie, at_hash.
3. The person's groups (`groups_claim` of the ID token, else of the UserInfo answer about the
   same subject) map to grants through `oidc.groups`: a role over depots, vehicles or the
   whole fleet per group, the strongest one holding per vehicle. No group mapped: refused.
4. The person's key row (made at their first sign-in, `sso_people`; it has no secret, so only
   their sessions use it) gets a session exactly as a key's login does
   (eqgw.security.sessions): the HttpOnly SameSite=Strict cookie, its CSRF token, logout,
   revocation. The session keeps this sign-in's grants until it ends (`session_max_age_s`):
   a change of groups at the provider counts from the next sign-in. The audit log names the
   person (subject, email) beside their key row.

Every refusal is a page (400, 401, 403, 404 or 502) that says what went wrong and leads back
to the login page.
"""

from __future__ import annotations

import asyncio
import html
import logging
import secrets
import time
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from fastapi import APIRouter, Request
from fastapi.responses import HTMLResponse, RedirectResponse, Response
from sqlalchemy import Engine
from sqlalchemy.exc import IntegrityError

from eqgw.config import OidcGroup
from eqgw.security import session_repository as sq
from eqgw.security.keys import (
    KEY_NAME_MAX,
    SSO_KEY_PREFIX,
    Grant,
    Person,
    Principal,
    Scope,
    hash_key,
    strongest,
)
from eqgw.security.sessions import secure_cookies, set_session_cookie, start_session
from eqgw.store.transaction import in_transaction
from eqgw.web.responses import JsonResponse
from eqgw.web.runtime import Runtime, runtime_of

if TYPE_CHECKING:
    from eqgw.security.oidc_provider import OidcProvider

log = logging.getLogger(__name__)

ROOT_PATH = "/auth/oidc"
LOGIN_PATH = f"{ROOT_PATH}/login"
CALLBACK_PATH = f"{ROOT_PATH}/callback"
LOGIN_COOKIE = "eqgw_oidc"
LOGIN_TTL_S = 600
ACTION = "session.sso"


class SignInRefused(Exception):
    """A sign-in that cannot go on: the HTTP status, and what the page tells the person."""

    def __init__(self, status: int, detail: str, *, person: Person | None = None) -> None:
        super().__init__(detail)
        self.status = status
        self.detail = detail
        self.person = person


def _unavailable(what: str) -> SignInRefused:
    return SignInRefused(502, f"The identity provider cannot be used: {what}.")


def _said(exc: Exception) -> str:
    return str(exc) or type(exc).__name__


@dataclass(frozen=True, slots=True)
class Identity:
    """Who the provider vouched for, from the checked ID token (and UserInfo)."""

    subject: str
    email: str | None
    name: str | None
    groups: tuple[str, ...]


@dataclass(frozen=True, slots=True)
class LoginState:
    """One sign-in's secrets, kept in the browser's `eqgw_oidc` cookie until the callback."""

    state: str
    nonce: str
    verifier: str

    @classmethod
    def new(cls) -> LoginState:
        return cls(secrets.token_urlsafe(24), secrets.token_urlsafe(24), secrets.token_urlsafe(48))

    def cookie(self) -> str:
        return f"{self.state}.{self.nonce}.{self.verifier}"

    @classmethod
    def of_cookie(cls, value: str | None) -> LoginState | None:
        parts = (value or "").split(".")
        if len(parts) != 3 or not all(parts):
            return None
        return cls(*parts)


def claim_values(claims: Mapping[str, Any], path: str) -> list[str] | None:
    """The strings of a claim (a dotted path reaches into objects, e.g. realm_access.roles);
    one string counts as a list of it; None when the claim is absent."""
    value: Any = claims
    for part in path.split("."):
        if not isinstance(value, Mapping) or part not in value:
            return None
        value = value[part]
    if isinstance(value, str):
        return [value]
    if isinstance(value, list):
        return [v for v in value if isinstance(v, str)]
    return []


def grants_for(
    groups: Iterable[str],
    mapping: Mapping[str, OidcGroup],
    depots: Mapping[str, str | None],
) -> tuple[Grant, ...]:
    """The grants of a person's groups (those `oidc.groups` maps; the others give nothing)."""
    grants = []
    for group in sorted(set(groups)):
        given = mapping.get(group)
        if given is None:
            continue
        scope = (
            Scope(None, None, depots)
            if given.all
            else Scope.of(given.depots, given.vehicles, depots)
        )
        grants.append(Grant(given.role, scope))
    return tuple(grants)


def describe_grants(grants: Iterable[Grant]) -> str:
    """What grants give, for the audit log: `operator of depots north; viewer of ...`."""
    parts = []
    for g in grants:
        listed = g.scope.as_json()
        if listed is None:
            parts.append(f"{g.role} of the whole fleet")
            continue
        where = []
        if listed["groups"]:
            where.append("depots " + ", ".join(listed["groups"]))
        if listed["vehicles"]:
            where.append("vehicles " + ", ".join(listed["vehicles"]))
        parts.append(f"{g.role} of {' and '.join(where)}")
    return "; ".join(parts)


# -- the routes ---------------------------------------------------------------------------------

router = APIRouter(include_in_schema=False)

_TITLES = {
    400: "This sign-in cannot go on",
    401: "Sign-in refused",
    403: "No access to this gateway",
    404: "Single sign-on is not set up",
    502: "The identity provider cannot be reached",
}


def refusal_page(status: int, detail: str) -> HTMLResponse:
    """The page of a refused sign-in: what went wrong, and the way back."""
    title = html.escape(_TITLES.get(status, "Sign-in failed"))
    body = f"""<!doctype html>
<html lang="en">
<head>
  <meta charset="utf-8">
  <meta name="viewport" content="width=device-width, initial-scale=1">
  <title>{title} · eqgw</title>
  <link rel="stylesheet" href="/static/css/app.css">
</head>
<body>
  <main id="main">
    <section class="login" id="sso-refused">
      <h1>{title}</h1>
      <p class="error" role="alert">{html.escape(detail)}</p>
      <p><a class="btn btn-primary" href="/">Back to the login page</a></p>
    </section>
  </main>
</body>
</html>
"""
    response = HTMLResponse(body, status_code=status, headers={"Cache-Control": "no-store"})
    response.delete_cookie(LOGIN_COOKIE, path=f"{ROOT_PATH}/", httponly=True, samesite="lax")
    return response


def provider_of(request: Request) -> OidcProvider:
    """The gateway's OpenID provider; a 404 refusal when single sign-on is not set up."""
    provider: OidcProvider | None = getattr(request.app.state, "oidc", None)
    if provider is None:
        raise SignInRefused(
            404, "This gateway has no single sign-on: log in with an API key or a login link."
        )
    return provider


def _redirect_uri(request: Request, rt: Runtime) -> str:
    """The callback address registered at the provider (the same at login and callback)."""
    configured = rt.settings.oidc.redirect_url
    if configured:
        return configured
    base = rt.api.public_url or str(request.base_url)
    return base.rstrip("/") + CALLBACK_PATH


@router.get(ROOT_PATH)
async def sso_info(request: Request) -> Response:
    """For the login page: whether to offer single sign-on, and how it is labelled."""
    provider = getattr(request.app.state, "oidc", None)
    if provider is None:
        return Response(status_code=404)
    return JsonResponse({"login_url": LOGIN_PATH, "label": provider.settings.label})


@router.get(LOGIN_PATH)
async def sso_login(request: Request) -> Response:
    """Start a sign-in: to the provider, this sign-in's secrets in the browser's cookie."""
    rt = runtime_of(request)
    try:
        provider = provider_of(request)
        login = LoginState.new()
        target = await provider.authorization_url(_redirect_uri(request, rt), login)
    except SignInRefused as refused:
        log.warning("single sign-on: %s", refused.detail)
        return refusal_page(refused.status, refused.detail)
    response = RedirectResponse(target, status_code=303, headers={"Cache-Control": "no-store"})
    response.set_cookie(
        LOGIN_COOKIE,
        login.cookie(),
        max_age=LOGIN_TTL_S,
        path=f"{ROOT_PATH}/",
        httponly=True,
        samesite="lax",
        secure=secure_cookies(request, rt),
    )
    return response


@router.get(CALLBACK_PATH)
async def sso_callback(request: Request) -> Response:
    """The provider's answer: check it all, then a session of the person (see the module)."""
    rt = runtime_of(request)
    try:
        provider = provider_of(request)
        principal, person_id = await _sign_in(rt, provider, request)
    except SignInRefused as refused:
        log.info("single sign-on refused (%s): %s", refused.status, refused.detail)
        await rt.audit(
            None,
            ACTION,
            outcome="refused",
            status=refused.status,
            detail=refused.detail,
            person=refused.person,
        )
        return refusal_page(refused.status, refused.detail)
    ttl = rt.settings.oidc.session_max_age_s
    token, _ = await start_session(rt, principal, ttl_s=ttl, person_id=person_id)
    await rt.audit(
        principal, ACTION, outcome="accepted", status=303, detail=describe_grants(principal.grants)
    )
    response = RedirectResponse("/", status_code=303, headers={"Cache-Control": "no-store"})
    set_session_cookie(response, request, rt, token, max_age_s=ttl)
    response.delete_cookie(LOGIN_COOKIE, path=f"{ROOT_PATH}/", httponly=True, samesite="lax")
    return response


async def _sign_in(rt: Runtime, provider: OidcProvider, request: Request) -> tuple[Principal, int]:
    """The principal (and person id) of a callback that passes every check."""
    query = request.query_params
    if "error" in query:
        said = query["error"]
        if "error_description" in query:
            said += f": {query['error_description']}"
        raise SignInRefused(403, f"The identity provider did not sign you in ({said}).")
    login = LoginState.of_cookie(request.cookies.get(LOGIN_COOKIE))
    if login is None:
        raise SignInRefused(
            400,
            "This sign-in was not started in this browser, or took longer than "
            f"{LOGIN_TTL_S // 60} minutes: start again from the login page.",
        )
    if not secrets.compare_digest(query.get("state", "").encode(), login.state.encode()):
        raise SignInRefused(
            400,
            "This answer does not belong to the sign-in this browser started (its state "
            "differs): start again from the login page.",
        )
    # RFC 9207: a provider that names itself must be ours (a mix-up with another provider).
    if "iss" in query and query["iss"] != provider.issuer:
        raise SignInRefused(400, f"This answer comes from {query['iss']!r}, not the provider.")
    code = query.get("code")
    if not code:
        raise SignInRefused(400, "The identity provider's answer holds no code.")
    answer = await provider.exchange(code, login, _redirect_uri(request, rt))
    who = await provider.identity(answer, login)
    person = Person(who.subject, who.email)
    depots = rt.keys.depots
    grants = grants_for(who.groups, rt.settings.oidc.groups, depots)
    if not grants:
        groups = ", ".join(sorted(set(who.groups))[:20]) if who.groups else "none"
        raise SignInRefused(
            403,
            f"You signed in as {who.email or who.name or who.subject}, but none of your groups "
            f"({groups}) gives access to this gateway. Ask the administrator of the identity "
            "provider to add you to a group that does.",
            person=person,
        )
    role = strongest(g.role for g in grants)
    scope = Scope.union((g.scope for g in grants), depots)
    name = _key_name(who)
    listed = scope.as_json()
    key = {
        "name": name,
        "role": role,
        "prefix": SSO_KEY_PREFIX,
        # A secret nobody is given: the person's key row works only through their sessions.
        "key_hash": hash_key(secrets.token_urlsafe(32)),
        "scope_groups": None if listed is None else listed["groups"],
        "scope_vehicles": None if listed is None else listed["vehicles"],
    }
    person_id, key_id = await asyncio.to_thread(_record, rt.engine, provider.issuer, who, key)
    principal = Principal(key_id, name, role, scope, person=person, grants=grants)
    return principal, person_id


def _key_name(who: Identity) -> str:
    """The name of a person's key row: their email (else name, else subject), marked SSO."""
    shown = who.email or who.name or who.subject
    shown = "".join(c if ord(c) >= 32 and not 127 <= ord(c) < 160 else " " for c in shown).strip()
    return f"{shown[: KEY_NAME_MAX - 10]} (SSO)"


def _record(engine: Engine, issuer: str, who: Identity, key: dict[str, Any]) -> tuple[int, int]:
    """The person's row and key row, made or updated (once more when two gateways made the
    person's first row at once)."""
    for attempt in (1, 2):
        try:
            # SQLite: the write lock from the start (a read that then writes fails at once
            # beside another writer, where a first write waits its busy timeout).
            return in_transaction(
                engine.execution_options(sqlite_begin="IMMEDIATE"),
                sq.person_key,
                issuer=issuer,
                subject=who.subject,
                email=who.email,
                name=who.name,
                key=key,
                now=time.time(),
            )
        except IntegrityError:
            if attempt == 2:
                raise
    raise AssertionError("unreachable")
