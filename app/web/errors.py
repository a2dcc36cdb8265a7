"""The one HTTP error type of the API and the handlers that turn errors into `{type, detail}`."""

from __future__ import annotations

import logging
from typing import Any

from fastapi import FastAPI, Request, Response
from fastapi.exceptions import RequestValidationError
from sqlalchemy.exc import InterfaceError, OperationalError, SQLAlchemyError
from sqlalchemy.exc import TimeoutError as SATimeoutError
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.routing import Match, Mount

from eqgw.bus.log_filters import RepeatSummaryFilter
from eqgw.describe import describe
from eqgw.web.responses import JsonResponse

log = logging.getLogger(__name__)

_TYPES = {
    400: "bad_request",
    401: "unauthorized",
    403: "forbidden",
    404: "not_found",
    405: "method_not_allowed",
    406: "not_acceptable",
    409: "conflict",
    413: "too_large",
    415: "unsupported_media_type",
    422: "validation_error",
    429: "rate_limited",
    500: "internal_error",
    503: "unavailable",
}


class ApiError(Exception):
    """An error the client should see: HTTP status, a stable `type` and a human `detail`."""

    def __init__(
        self,
        status: int,
        detail: str,
        type_: str | None = None,
        *,
        headers: dict[str, str] | None = None,
        extra: dict[str, Any] | None = None,
    ) -> None:
        super().__init__(detail)
        self.status = status
        self.type = type_ or _TYPES.get(status, "error")
        self.detail = detail
        self.headers = headers
        self.extra = extra or {}

    def body(self) -> dict[str, Any]:
        return {"type": self.type, "detail": self.detail, **self.extra}


def _response(err: ApiError) -> JsonResponse:
    return JsonResponse(err.body(), status_code=err.status, headers=err.headers)


async def _api_error(_request: Request, exc: Exception) -> JsonResponse:
    assert isinstance(exc, ApiError)
    return _response(exc)


_METHODS = ("GET", "HEAD", "POST", "PUT", "PATCH", "DELETE")


def allowed_methods(request: Request) -> list[str]:
    """Every method of the request's path: those some route takes there (FastAPI makes one
    route per method, and the router's 405 names only the first one's), and OPTIONS, which is
    answered for every path. Empty when no route has the path."""
    # A mount (the static files) takes any method to its app, which answers for itself.
    routes = [r for r in request.app.router.routes if not isinstance(r, Mount)]
    methods = {
        method
        for method in _METHODS
        if any(
            route.matches({**request.scope, "method": method})[0] is Match.FULL for route in routes
        )
    }
    return sorted(methods | {"OPTIONS"}) if methods else []


async def _http_error(request: Request, exc: Exception) -> Response:
    assert isinstance(exc, StarletteHTTPException)
    headers = dict(exc.headers) if exc.headers else None
    if exc.status_code == 405:
        allowed = allowed_methods(request)
        if allowed:
            headers = {**(headers or {}), "Allow": ", ".join(allowed)}
            if request.method == "OPTIONS":
                return Response(status_code=204, headers=headers)
    return _response(ApiError(exc.status_code, str(exc.detail), headers=headers))


async def _validation_error(request: Request, exc: Exception) -> JsonResponse:
    assert isinstance(exc, RequestValidationError)
    errors = [{"loc": list(e.get("loc", ())), "msg": str(e.get("msg", ""))} for e in exc.errors()]
    detail = "; ".join(f"{'.'.join(map(str, e['loc']))}: {e['msg']}" for e in errors)
    # A body that is not JSON at all is a 400; one that is JSON but not the schema, a 422.
    status = 400 if any(e.get("type") == "json_invalid" for e in exc.errors()) else 422
    detail = detail or "invalid request"
    if status == 400:
        detail = f"the body is not valid JSON ({detail})"
    on_refused = getattr(request.app.state, "on_invalid_write", None)
    if on_refused is not None:
        await on_refused(request, status, detail, exc.body)
    return _response(ApiError(status, detail, extra={"errors": errors}))


# What `_validation_error` answers, documented in place of FastAPI's default 422 body (a list of
# pydantic errors under `detail`), which every route with parameters would otherwise promise.
VALIDATION_ERROR_SCHEMA: dict[str, Any] = {
    "title": "ValidationErrorBody",
    "type": "object",
    "required": ["type", "detail"],
    "properties": {
        "type": {"type": "string"},
        "detail": {"type": "string"},
        "errors": {
            "type": "array",
            "items": {
                "type": "object",
                "required": ["loc", "msg"],
                "properties": {
                    "loc": {"type": "array", "items": {"type": ["string", "integer"]}},
                    "msg": {"type": "string"},
                },
            },
        },
    },
}


def _document_validation_errors(app: FastAPI) -> None:
    generate = app.openapi

    def openapi() -> dict[str, Any]:
        if app.openapi_schema is None:
            schema = generate()
            components = schema.get("components", {}).get("schemas", {})
            if "HTTPValidationError" in components:
                components["HTTPValidationError"] = VALIDATION_ERROR_SCHEMA
                components.pop("ValidationError", None)
            app.openapi_schema = schema
        return app.openapi_schema

    app.openapi = openapi  # type: ignore[method-assign]


# While the database is away every request fails alike: said once per 10 s, with a count.
_DB_DOWN = "API request failed, the database is unavailable"
log.addFilter(RepeatSummaryFilter([_DB_DOWN], interval=10.0))


def _unavailable(exc: Exception) -> bool:
    """Whether a database error is the database being away (not a bug of ours)."""
    return isinstance(exc, OperationalError | InterfaceError | SATimeoutError) or bool(
        getattr(exc, "connection_invalidated", False)
    )


async def _database_error(_request: Request, exc: Exception) -> JsonResponse:
    if not _unavailable(exc):
        raise exc  # a bug: the 500 handler answers it and the server logs the traceback
    reason = describe(exc)
    log.warning("%s: %s", _DB_DOWN, reason)
    return _response(
        ApiError(
            503,
            f"the database is unavailable ({reason}); retry shortly",
            headers={"Retry-After": "5"},
        )
    )


async def _internal_error(_request: Request, _exc: Exception) -> JsonResponse:
    # The server logs the exception with its traceback after this answer.
    return _response(ApiError(500, "internal error (logged by the gateway)"))


def install_error_handlers(app: FastAPI) -> None:
    """Map every error the API raises to the JSON error body, and document that body."""
    app.add_exception_handler(ApiError, _api_error)
    app.add_exception_handler(StarletteHTTPException, _http_error)
    app.add_exception_handler(RequestValidationError, _validation_error)
    # The database away: a 503 with Retry-After in the JSON error body (the server goes on,
    # the ingest's writer holds rows and retries); anything else unexpected: a JSON 500.
    app.add_exception_handler(SQLAlchemyError, _database_error)  # the pool's timeout too
    app.add_exception_handler(Exception, _internal_error)
    _document_validation_errors(app)
