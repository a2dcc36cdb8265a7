"""Dashboard logins: an API key exchanged once for an HttpOnly session cookie.

The key never stays in the browser: `POST /session` (the login form) or the first-start link
`/?key=...` (answered by a redirect to `/` without it) creates a session row holding the key's
id and sets `eqgw_session` (HttpOnly, SameSite=Strict, Secure over https). Every request
resolves the session's key again (cached for `key_cache_s`), so revoking the key ends its
sessions. Writes by cookie carry the session's CSRF token in `X-CSRF-Token`;
`DELETE /session` ends the session on the server.
"""

from __future__ import annotations

import secrets
import time
from typing import Any
from urllib.parse import urlencode

from fastapi import APIRouter, Request
from fastapi.responses import RedirectResponse, Response
from pydantic import Field

from eqgw.api.auth import INGEST, Principal, hash_key
from eqgw.api.deps import (
    CSRF_HEADER,
    SESSION_COOKIE,
    Runtime,
    authenticate,
    authenticate_session,
    runtime_of,
    session_cookie,
)
from eqgw.api.errors import ApiError
from eqgw.api.read_schemas import SessionInfo
from eqgw.api.responses import JsonResponse
from eqgw.api.schemas import RequestBody, errors
from eqgw.store import session_queries as sq

router = APIRouter(tags=["session"])


class Login(RequestBody):
    """An API key to log in with (it is not kept: the session stands for it)."""

    key: str = Field(min_length=1, max_length=200)


def _secure(request: Request, rt: Runtime) -> bool:
    return request.url.scheme == "https" or (rt.api.public_url or "").startswith("https:")


async def _start(rt: Runtime, principal: Principal) -> tuple[str, str]:
    """A new session of `principal`'s key: (cookie token, CSRF token)."""
    token = secrets.token_urlsafe(32)
    csrf = secrets.token_urlsafe(32)
    await rt.db(
        sq.create_session,
        token_hash=hash_key(token),
        key_id=principal.key_id,
        csrf_token=csrf,
        now=time.time(),
        ttl_s=rt.api.session_max_age_s,
    )
    return token, csrf


def _set_cookie(response: Response, request: Request, rt: Runtime, token: str) -> None:
    response.set_cookie(
        SESSION_COOKIE,
        token,
        max_age=int(rt.api.session_max_age_s),
        path="/",
        httponly=True,
        samesite="strict",
        secure=_secure(request, rt),
    )


def _me(principal: Principal, csrf: str) -> dict[str, Any]:
    return {
        "key_id": principal.key_id,
        "name": principal.name,
        "role": principal.role,
        "scope": principal.scope.as_json(),
        "csrf_token": csrf,
    }


async def _login_principal(rt: Runtime, key: str) -> Principal:
    principal = await authenticate(rt, key)
    if principal is None:
        raise ApiError(401, "that key is unknown or revoked")
    if principal.role == INGEST:
        raise ApiError(403, "an ingest key cannot log in to the dashboard")
    return principal


@router.post(
    "/session",
    status_code=201,
    summary="Log in: exchange an API key for a session cookie (the dashboard's login)",
    responses=errors(400, 401, 403, 422),
    response_model=SessionInfo,
)
async def login(body: Login, request: Request) -> JsonResponse:
    rt = runtime_of(request)
    principal = await _login_principal(rt, body.key.strip())
    token, csrf = await _start(rt, principal)
    response = JsonResponse(_me(principal, csrf), status_code=201)
    _set_cookie(response, request, rt, token)
    return response


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
    response = Response(status_code=204)
    response.delete_cookie(SESSION_COOKIE, path="/", httponly=True, samesite="strict")
    return response


async def login_from_url(request: Request) -> Response | None:
    """`/?key=...` (the link `eqgw serve` prints): a session for the key and a redirect to
    the same address without it, so the key stays out of the page, its Referer headers and
    its websocket URL. None when the address has no key."""
    key = request.query_params.get("key")
    if key is None:
        return None
    rest = [(k, v) for k, v in request.query_params.multi_items() if k != "key"]
    target = "/" + ("?" + urlencode(rest) if rest else "")
    response = RedirectResponse(target, status_code=303, headers={"Cache-Control": "no-store"})
    rt: Runtime | None = getattr(request.app.state, "rt", None)
    if rt is None:
        return response
    try:
        principal = await _login_principal(rt, key.strip())
    except ApiError:
        return response  # the page shows its login form
    token, _ = await _start(rt, principal)
    _set_cookie(response, request, rt, token)
    return response
