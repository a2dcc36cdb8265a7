"""Times in query parameters, read the same way by every route: epoch seconds or ISO 8601,
and the `from`/`to` of a series or of a list filter (a 422 `invalid_time` otherwise)."""

from __future__ import annotations

import math
import time
from datetime import UTC, datetime

from eqgw.web.errors import ApiError


def parse_time(value: str | None, default: float, name: str | None = None) -> float:
    """Epoch seconds or ISO 8601 (naive = UTC) to epoch seconds; `default` when absent.

    Anything else is a 422 naming the parameter `name`: NaN and the infinities too (`nan`,
    `inf`, `1e400`), which `float()` accepts but no time is.
    """
    if value is None or value == "":
        return default
    what = f"`{name}`: " if name else ""
    try:
        t = float(value)
    except ValueError:
        pass
    else:
        if not math.isfinite(t):
            raise ApiError(
                422, f"{what}{value!r} is not a finite number of epoch seconds", "invalid_time"
            )
        return t
    try:
        dt = datetime.fromisoformat(value.replace("Z", "+00:00"))
    except ValueError as exc:
        raise ApiError(
            422, f"{what}{value!r} is neither epoch seconds nor an ISO 8601 time", "invalid_time"
        ) from exc
    if dt.tzinfo is None:
        dt = dt.replace(tzinfo=UTC)
    return dt.timestamp()


def _check_order(start: float | None, end: float | None) -> None:
    if start is not None and end is not None and not end > start:
        raise ApiError(422, "`from` must be before `to`", "invalid_time")


def time_window(from_: str | None, to: str | None, span: float) -> tuple[float, float]:
    """`from`/`to` of a series: `to` defaults to now, `from` to `span` seconds before `to`;
    each checked by `parse_time`, and `from` before `to`."""
    end = parse_time(to, time.time(), "to")
    start = parse_time(from_, end - span, "from")
    _check_order(start, end)
    return start, end


def time_filter(from_: str | None, to: str | None) -> tuple[float | None, float | None]:
    """`from`/`to` of a list filter: absent (or empty) is None, no bound; each given one is
    checked by `parse_time`, and `from` must be before `to` when both are given."""
    start = parse_time(from_, 0.0, "from") if from_ else None
    end = parse_time(to, 0.0, "to") if to else None
    _check_order(start, end)
    return start, end
