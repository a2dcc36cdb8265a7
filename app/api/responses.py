"""A JSON response rendered with orjson: the live endpoints return plain dicts, fast."""

from __future__ import annotations

from typing import Any

import orjson
from starlette.responses import Response


class JsonResponse(Response):
    """`application/json` via orjson (NaN and infinities become null)."""

    media_type = "application/json"

    def render(self, content: Any) -> bytes:
        return orjson.dumps(content, option=orjson.OPT_NON_STR_KEYS)


def dumps(content: Any) -> bytes:
    """orjson with the options every API body uses."""
    return orjson.dumps(content, option=orjson.OPT_NON_STR_KEYS)
