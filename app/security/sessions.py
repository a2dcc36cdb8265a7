"""Dashboard logins: an API key, or a one-time login code, exchanged for an HttpOnly session
cookie.

The key never stays in the browser: `POST /session` (the login form's key, or the code of a
login link, app/security/login_codes.py) creates a session row holding the key's id and sets
`eqgw_session` (HttpOnly, SameSite=Strict, Secure over https). A login sent by another site's
page (`Sec-Fetch-Site`, `Origin`) is refused: no site can log a browser into a session of its
choosing. A key in the dashboard's address (`/?key=...`) logs no one in. Every request
resolves the session's key again (cached for `key_cache_s`), so revoking the key ends its
sessions. Writes by cookie carry the session's CSRF token in `X-CSRF-Token`;
`DELETE /session` ends the session on the server.
"""

from __future__ import annotations

import secrets
import time
from typing import Any
from urllib.parse import urlencode, urlsplit

from fastapi import APIRouter, Depends, Request
from fastapi.responses import RedirectResponse, Response
from pydantic import BaseModel, ConfigDict, Field, model_validator

from eqgw.security import session_repository as sq
from eqgw.security.auth import (
    CSRF_HEADER,
    SESSION_COOKIE,
    authenticate,
    authenticate_session,
    session_cookie,
)
from eqgw.security.keys import INGEST, Principal, _active, hash_key
from eqgw.security.schemas import ScopeOut, SessionInfo
from eqgw.web.errors import ApiError
from eqgw.web.responses import JsonResponse
from eqgw.web.runtime import Runtime, runtime_of
from eqgw.web.schemas import RequestBody, _body_schema, errors

router = APIRouter(tags=["session"])


def _key_or_code(schema: dict[str, Any]) -> None:
    _body_schema(schema)
    # Exactly one of the two, as the validator checks.
    schema["oneOf"] = [
        {"required": [name], "properties": {name: {"type": "string"}}} for name in ("key", "code")
    ]


class Login(RequestBody):
    """An API key, or the one-time code of a login link, to log in with (neither is kept:
    the session stands for the key)."""

    model_config = ConfigDict(json_schema_extra=_key_or_code)

    key: str | None = Field(default=None, min_length=1, max_length=200)
    code: str | None = Field(
        default=None, min_length=1, max_length=200, description="a login link's one-time code"
    )

    @model_validator(mode="after")
    def _one(self) -> Login:
        if (self.key is None) == (self.code is None):
            raise ValueError("give either key or code")
        return self


class CodeQuery(RequestBody):
    """A login link's one-time code (not used up by asking)."""

    code: str = Field(min_length=1, max_length=200)


class CodeInfo(BaseModel):
    """Whom a login code logs in as, for the page to ask before it does."""

    name: str
    role: str = Field(description="viewer, operator or admin")
    scope: ScopeOut | None = Field(
        default=None, description="the vehicles the key reaches; null: the whole fleet"
    )
    expires_at: float = Field(description="when the code stops working (epoch s)")


def secure_cookies(request: Request, rt: Runtime) -> bool:
    """Whether cookies get `Secure`: served over https, or behind an https public URL."""
    return request.url.scheme == "https" or (rt.api.public_url or "").startswith("https:")


async def start_session(
    rt: Runtime,
    principal: Principal,
    *,
    ttl_s: float | None = None,
    person_id: int | None = None,
) -> tuple[str, str]:
    """A new session of `principal`'s key (a person's, with their grants, for single
    sign-on), lasting `ttl_s` (default `session_max_age_s`): (cookie token, CSRF token)."""
    token = secrets.token_urlsafe(32)
    csrf = secrets.token_urlsafe(32)
    await rt.db(
        sq.create_session,
        token_hash=hash_key(token),
        key_id=principal.key_id,
        csrf_token=csrf,
        now=time.time(),
        ttl_s=rt.api.session_max_age_s if ttl_s is None else ttl_s,
        person_id=person_id,
        grants=[g.as_json() for g in principal.grants] if principal.grants else None,
    )
    return token, csrf


def set_session_cookie(
    response: Response, request: Request, rt: Runtime, token: str, max_age_s: float | None = None
) -> None:
    """Give the browser its session cookie (HttpOnly, SameSite=Strict, Secure over https)."""
    response.set_cookie(
        SESSION_COOKIE,
        token,
        max_age=int(rt.api.session_max_age_s if max_age_s is None else max_age_s),
        path="/",
        httponly=True,
        samesite="strict",
        secure=secure_cookies(request, rt),
    )


def who_json(principal: Principal) -> dict[str, Any]:
    """Who a key or session is, as `/me` and `/session` say it."""
    person = principal.person
    return {
        "key_id": principal.key_id,
        "name": principal.name,
        "role": principal.role,
        "scope": principal.scope.as_json(),
        "person": None if person is None else {"subject": person.subject, "email": person.email},
        "grants": [g.as_json() for g in principal.grants] if principal.grants else None,
    }


def _me(principal: Principal, csrf: str) -> dict[str, Any]:
    return {**who_json(principal), "csrf_token": csrf}


def _dashboard(principal: Principal | None, unknown: str) -> Principal:
    if principal is None:
        raise ApiError(401, unknown)
    if principal.role == INGEST:
        raise ApiError(403, "an ingest key cannot log in to the dashboard")
    return principal


async def _login_principal(rt: Runtime, key: str) -> Principal:
    return _dashboard(await authenticate(rt, key), "that key is unknown or revoked")


_CODE_UNKNOWN = "that login code is unknown, used up or expired; ask for a new link"


async def _code_principal(
    rt: Runtime, code: str, *, consume: bool
) -> tuple[Principal, dict[str, Any]]:
    """The key a login code stands for, and its row; with `consume`, the code is used up
    (once only, on whichever gateway asks first)."""
    now = time.time()
    query = sq.consume_login_code if consume else sq.login_code_key
    row = await rt.db(query, hash_key(code.strip()), now)
    principal = _active(row, now, rt.keys.depots) if row is not None else None
    return _dashboard(principal, _CODE_UNKNOWN), row or {}


async def same_origin(request: Request) -> None:
    """A 403 for a login another site's page sent (login CSRF: it would log the browser into
    the other site's key), before its body is looked at. Browsers say where a request comes
    from: `Sec-Fetch-Site`, and `Origin` on every POST by a page; clients that send neither
    (curl, scripts) are let in."""
    rt = runtime_of(request)
    site = request.headers.get("sec-fetch-site")
    if site is not None and site not in ("same-origin", "none"):
        raise ApiError(403, f"a login from another site is refused (Sec-Fetch-Site: {site})")
    origin = request.headers.get("origin")
    if origin is None:
        return
    ours = {request.headers.get("host", "").lower()}
    if rt.api.public_url:
        ours.add(urlsplit(rt.api.public_url).netloc.lower())
    if urlsplit(origin).netloc.lower() not in ours:
        raise ApiError(403, "a login from another site is refused (Origin)")


@router.post(
    "/session",
    status_code=201,
    summary="Log in: exchange an API key or a login link's code for a session cookie",
    responses=errors(400, 401, 403, 422),
    response_model=SessionInfo,
    dependencies=[Depends(same_origin)],
)
async def login(body: Login, request: Request) -> JsonResponse:
    rt = runtime_of(request)
    if body.code is not None:
        principal, _ = await _code_principal(rt, body.code, consume=True)
    else:
        assert body.key is not None
        principal = await _login_principal(rt, body.key.strip())
    token, csrf = await start_session(rt, principal)
    response = JsonResponse(_me(principal, csrf), status_code=201)
    set_session_cookie(response, request, rt, token)
    return response


@router.post(
    "/session/code",
    summary="Whom a login link's code logs in as (the code is not used up)",
    responses=errors(400, 401, 403, 422),
    response_model=CodeInfo,
)
async def code_info(body: CodeQuery, request: Request) -> JsonResponse:
    rt = runtime_of(request)
    principal, row = await _code_principal(rt, body.code, consume=False)
    return JsonResponse(
        {
            "name": principal.name,
            "role": principal.role,
            "scope": principal.scope.as_json(),
            "expires_at": row["code_expires_at"],
        }
    )


@router.get(
    "/session",
    summary="The session of the cookie: who, and the CSRF token its writes carry",
    responses=errors(401),
    response_model=SessionInfo,
)
async def current(request: Request) -> JsonResponse:
    rt = runtime_of(request)
    session = await authenticate_session(rt, session_cookie(request.headers))
    if session is None:
        raise ApiError(401, "no session: log in")
    return JsonResponse(_me(session.principal, session.csrf_token))


@router.delete(
    "/session",
    status_code=204,
    summary=f"Log out: end the session on the server (needs {CSRF_HEADER})",
    responses=errors(401, 403),
)
async def logout(request: Request) -> Response:
    rt = runtime_of(request)
    session = await authenticate_session(rt, session_cookie(request.headers))
    if session is None:
        raise ApiError(401, "no session: log in")
    if not secrets.compare_digest(request.headers.get(CSRF_HEADER, ""), session.csrf_token):
        raise ApiError(403, f"logging out needs the session's {CSRF_HEADER} header", "csrf")
    await rt.db(sq.delete_session, session.token_hash)
    rt.keys.forget()
    if session.principal.person is not None:
        await rt.audit(session.principal, "session.logout", outcome="accepted", status=204)
    response = Response(status_code=204)
    response.delete_cookie(SESSION_COOKIE, path="/", httponly=True, samesite="strict")
    return response


def key_in_url(request: Request) -> Response | None:
    """`/?key=...` (an old login link, or one another site made): a redirect to the same
    address without the key, and no session (a key in an address would log the browser in
    as whoever made the link). None when the address has no key."""
    if "key" not in request.query_params:
        return None
    rest = [(k, v) for k, v in request.query_params.multi_items() if k != "key"]
    target = "/" + ("?" + urlencode(rest) if rest else "")
    return RedirectResponse(target, status_code=303, headers={"Cache-Control": "no-store"})
