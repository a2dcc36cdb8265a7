"""A JSON response rendered with orjson: the live endpoints return plain dicts, fast."""

from __future__ import annotations

import json
import math
from typing import Any

import orjson
from starlette.responses import JSONResponse


class JsonResponse(JSONResponse):
    """`application/json` via orjson (NaN and infinities become null).

    A JSONResponse subclass so FastAPI documents the routes' response models in the OpenAPI
    schema (for any other response class it documents a bare string).
    """

    def render(self, content: Any) -> bytes:
        return dumps(content)


def dumps(content: Any) -> bytes:
    """orjson with the options every API body uses.

    orjson refuses integers beyond 64 bits, which a client can put in a request body that is
    then stored (the audit log keeps refused requests as sent); those bodies go through the
    standard library instead, exact and still valid JSON.
    """
    try:
        return orjson.dumps(content, option=orjson.OPT_NON_STR_KEYS)
    except TypeError:
        return json.dumps(_plain(content), separators=(",", ":"), allow_nan=False).encode()


def _plain(value: Any) -> Any:
    """What orjson would make of `value`, for the standard library (keys as text, NaN as null)."""
    if isinstance(value, dict):
        return {str(k) if not isinstance(k, str) else k: _plain(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_plain(v) for v in value]
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value
