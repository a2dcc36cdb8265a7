"""What every request passes before the app: security headers, body bounds, early auth, NUL.

A pure ASGI middleware (no body buffering of its own):
- every HTTP response gets `X-Content-Type-Options: nosniff`, `Referrer-Policy: no-referrer`,
  `X-Frame-Options: DENY` and a Content-Security-Policy without inline script;
- a request body is bounded per route (forwarder uploads larger): a `Content-Length` past the
  bound is a 413 before anything is read, and a streamed body is counted and cut at the bound;
  a body slower than `body_timeout_s` is a 408;
- a request with a body to the API is authenticated from its headers first: without a valid
  key or session, its body is never read (the route answers its 401 as usual);
- a path or query string holding a NUL character (which PostgreSQL text cannot hold) or a lone
  surrogate is a 422 before any route runs.
"""

from __future__ import annotations

import asyncio
import logging
import re
from typing import Any
from urllib.parse import unquote

import orjson
from starlette.exceptions import HTTPException
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from eqgw.store.engine import db_deadline, restart_deadline
from eqgw.web.schemas import bad_text
from eqgw.web.settings import ApiSettings

# The dashboard's policy: scripts, styles and connections from this origin only.
DASHBOARD_CSP = (
    "default-src 'self'; script-src 'self'; style-src 'self'; img-src 'self' data:; "
    "connect-src 'self'; font-src 'self'; object-src 'none'; base-uri 'none'; "
    "form-action 'self'; frame-ancestors 'none'"
)
# The interactive docs page: Swagger UI from the gateway's own files (static/vendor), started
# by FastAPI's one inline script; nothing from another origin.
DOCS_CSP = (
    "default-src 'self'; script-src 'self' 'unsafe-inline'; style-src 'self' 'unsafe-inline'; "
    "img-src 'self' data:; worker-src 'self' blob:; connect-src 'self'; object-src 'none'; "
    "base-uri 'none'; frame-ancestors 'none'"
)
DOCS_PATHS = ("/docs",)
_BASE_HEADERS = [
    (b"x-content-type-options", b"nosniff"),
    (b"referrer-policy", b"no-referrer"),
    (b"x-frame-options", b"DENY"),
]
INGEST_PREFIX = "/api/v1/ingest/"
LOGIN_PATHS = frozenset({"/api/v1/session", "/api/v1/session/code"})
# Routes whose database work is one long transaction (a CSV import of the fleet): they get
# `import_deadline_s` instead of `db_deadline_s`.
LONG_PATHS = frozenset({"/api/v1/vehicles/import"})
_BODY_METHODS = {"POST", "PUT", "PATCH", "DELETE"}
SAFE_METHODS = {"GET", "HEAD", "OPTIONS"}
# Past a request's database deadline, what its own deadline may still take (a connection
# being given up) before the request is answered 503 regardless.
DEADLINE_GRACE_S = 0.5
_VEHICLE_IN_PATH = re.compile(r"/api/v1/vehicles/([^/]+)")
log = logging.getLogger(__name__)


def _error(status: int, type_: str, detail: str) -> tuple[dict[str, Any], bytes]:
    body = orjson.dumps({"type": type_, "detail": detail})
    start = {
        "type": "http.response.start",
        "status": status,
        "headers": [
            (b"content-type", b"application/json"),
            (b"content-length", str(len(body)).encode()),
            (b"connection", b"close"),
        ],
    }
    return start, body


class RequestGuard:
    """The middleware (see the module's docstring)."""

    def __init__(self, app: ASGIApp, api: ApiSettings | None = None) -> None:
        self.app = app
        self.api = api or ApiSettings()

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] == "http" and not str(scope.get("path", "")).startswith(INGEST_PREFIX):
            # The request's database work (its key, its queries) ends within the deadline:
            # a database that does not answer costs a 503 with Retry-After, never a hang.
            limit = (
                self.api.import_deadline_s
                if scope.get("path") in LONG_PATHS
                else self.api.db_deadline_s
            )
            with db_deadline(limit):
                await self._within_deadline(scope, receive, send, limit)
            return
        await self._call(scope, receive, send)

    async def _within_deadline(
        self, scope: Scope, receive: Receive, send: Send, limit: float
    ) -> None:
        """The request, answered 503 if it has not begun its answer `limit` seconds (plus a
        moment) after it could start: its start, or for a request with a body, the body's
        end (the deadline of its database work restarts there too). The work's own deadline
        ends it normally; this holds whatever a worker thread is stuck in."""
        loop = asyncio.get_running_loop()
        ready_at: list[float] = [loop.time()] if scope["method"] in SAFE_METHODS else []
        started = False

        async def received() -> Message:
            message = await receive()
            if not ready_at and not message.get("more_body", False):
                ready_at.append(loop.time())
                restart_deadline(limit)
            return message

        async def tracked(message: Message) -> None:
            nonlocal started
            if message["type"] == "http.response.start":
                started = True
            await send(message)

        task = asyncio.ensure_future(self._call(scope, received, tracked))
        try:
            while not task.done():
                if started or not ready_at:
                    await asyncio.wait({task}, timeout=0.5 if not started else None)
                    continue
                left = ready_at[0] + limit + DEADLINE_GRACE_S - loop.time()
                if left <= 0:
                    break
                await asyncio.wait({task}, timeout=left)
        except BaseException:
            task.cancel()
            raise
        if task.done():
            task.result()
            return
        task.cancel()
        await asyncio.wait({task}, timeout=1.0)
        log.warning("%s %s: no answer within %.1f s; 503", scope["method"], scope["path"], limit)
        start, body = _error(
            503, "unavailable", "the database did not answer in time; retry shortly"
        )
        start["headers"].append((b"retry-after", b"5"))
        send = self._with_headers(scope, send)
        await send(start)
        await send({"type": "http.response.body", "body": body})

    async def _call(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] not in ("http", "websocket"):
            await self.app(scope, receive, send)
            return
        reason = self._bad_target(scope)
        if scope["type"] == "websocket":
            if reason is not None:
                await send({"type": "websocket.close", "code": 1008, "reason": reason})
                return
            await self.app(scope, receive, send)
            return
        send = self._with_headers(scope, send)
        if reason is not None:
            if scope["method"] not in SAFE_METHODS:
                await self._audit_refusal(scope, reason)
            await self._refuse(send, 422, "validation_error", reason)
            return
        path: str = scope["path"]
        bound = (
            self.api.ingest_max_body_bytes
            if path.startswith(INGEST_PREFIX)
            else self.api.max_body_bytes
        )
        length = _header(scope, b"content-length")
        if length is not None:
            try:
                declared = int(length)
            except ValueError:
                await self._refuse(send, 400, "bad_request", "Content-Length is not a number")
                return
            if declared > bound:
                await self._refuse(
                    send, 413, "too_large", f"the body is over this route's {bound} bytes"
                )
                return
        if (
            scope["method"] in _BODY_METHODS
            and path.startswith("/api/")
            and path not in LOGIN_PATHS
            and not await self._authenticated(scope)
        ):
            # Unauthenticated: the route sees an empty body and answers its 401 (audited
            # like any refused write); what the client sends is never read.
            receive = _withheld()
        else:
            receive = self._bounded(receive, bound)
        await self.app(scope, receive, send)

    @staticmethod
    def _bad_target(scope: Scope) -> str | None:
        query = scope.get("query_string", b"")
        try:
            texts = [scope["path"], unquote(query.decode("latin-1"), errors="surrogateescape")]
        except UnicodeDecodeError:
            return "the query string is not valid UTF-8"
        for text in texts:
            reason = bad_text(text)
            if reason is not None:
                return f"in the URL: {reason}"
        return None

    async def _audit_refusal(self, scope: Scope, reason: str) -> None:
        """A write refused here is audited like one refused by its route."""
        from eqgw.security.auth import resolve_headers

        rt = getattr(getattr(scope.get("app"), "state", None), "rt", None)
        if rt is None:
            return
        try:
            resolved = await resolve_headers(rt, _headers(scope))
            vehicle = _VEHICLE_IN_PATH.match(scope["path"])
            await rt.audit(
                resolved[0] if resolved else None,
                f"{scope['method']} {scope['path']}",
                outcome="refused",
                status=422,
                detail=reason,
                vehicle_id=vehicle[1] if vehicle else None,
            )
        except Exception:  # the database away: the refusal still stands
            log.warning("a refused write could not be audited", exc_info=True)

    async def _authenticated(self, scope: Scope) -> bool:
        from eqgw.security.auth import remember_auth, resolve_headers

        app = scope.get("app")
        rt = getattr(getattr(app, "state", None), "rt", None)
        if rt is None:
            return True  # not serving yet: routes answer 503 themselves
        try:
            auth = await resolve_headers(rt, _headers(scope))
        except Exception:  # the database away: let the route answer (its own 503)
            return True
        remember_auth(scope, auth)  # the route's dependency takes it instead of asking again
        return auth is not None

    def _bounded(self, receive: Receive, bound: int) -> Receive:
        seen = 0
        timeout = self.api.body_timeout_s
        deadline: float | None = None

        async def bounded() -> Message:
            nonlocal seen, deadline
            loop = asyncio.get_running_loop()
            if deadline is None:
                deadline = loop.time() + timeout
            try:
                async with asyncio.timeout_at(deadline):
                    message = await receive()
            except TimeoutError:
                raise HTTPException(408, f"the body did not arrive within {timeout:g} s") from None
            if message["type"] == "http.request":
                seen += len(message.get("body", b""))
                if seen > bound:
                    raise HTTPException(413, f"the body is over this route's {bound} bytes")
            return message

        return bounded

    def _with_headers(self, scope: Scope, send: Send) -> Send:
        path: str = scope["path"]
        csp = DOCS_CSP if path.startswith(DOCS_PATHS) else DASHBOARD_CSP
        extra = [*_BASE_HEADERS, (b"content-security-policy", csp.encode())]

        async def wrapped(message: Message) -> None:
            if message["type"] == "http.response.start":
                have = {k.lower() for k, _ in message.get("headers", [])}
                headers = list(message.get("headers", []))
                headers.extend((k, v) for k, v in extra if k not in have)
                message = {**message, "headers": headers}
            await send(message)

        return wrapped

    @staticmethod
    async def _refuse(send: Send, status: int, type_: str, detail: str) -> None:
        start, body = _error(status, type_, detail)
        await send(start)
        await send({"type": "http.response.body", "body": body})


def _withheld() -> Receive:
    """A receive that gives the app an empty body and never reads the client's."""
    given = False

    async def receive() -> Message:
        nonlocal given
        if not given:
            given = True
            return {"type": "http.request", "body": b"", "more_body": False}
        await asyncio.Future()  # nothing more, ever (the response does not wait for it)
        raise AssertionError("unreachable")

    return receive


def _header(scope: Scope, name: bytes) -> str | None:
    for k, v in scope.get("headers", []):
        if k.lower() == name:
            return str(v.decode("latin-1"))
    return None


def _headers(scope: Scope) -> dict[str, str]:
    return {k.decode("latin-1").lower(): v.decode("latin-1") for k, v in scope["headers"]}
