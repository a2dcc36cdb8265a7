"""What routes' request bodies and errors share: `RequestBody` (text the database cannot store
refused), the error body and `errors(...)` for a route's documented error answers, `MAX_ID`.
The domains' own shapes are in their packages (`eqgw.commands.schemas`,
`eqgw.security.schemas`, ...)."""

from __future__ import annotations

import math
from typing import Any, ClassVar

from pydantic import BaseModel, ConfigDict, model_validator


def bad_text(text: str) -> str | None:
    """Why a request string cannot be stored (a NUL character, a lone surrogate), or None."""
    if "\x00" in text:
        return "NUL characters are not accepted"
    try:
        text.encode("utf-8")
    except UnicodeEncodeError:
        return "text must be valid UTF-8 (a lone surrogate is not)"
    return None


def nul_at(data: Any, where: tuple[str, ...] = ()) -> tuple[str, ...] | None:
    """Where in parsed JSON a text (a value or a key) cannot be stored, or None: a NUL
    character (PostgreSQL text cannot hold one) or a lone surrogate (not UTF-8); or a number
    that is NaN or infinite (JSON cannot hold one; Python's parser accepts them)."""
    if isinstance(data, str):
        return where if bad_text(data) is not None else None
    if isinstance(data, float):
        return None if math.isfinite(data) else where
    if isinstance(data, dict):
        for k, v in data.items():
            found = nul_at(k, (*where, str(k))) or nul_at(v, (*where, str(k)))
            if found is not None:
                return found
    elif isinstance(data, list | tuple):
        for i, v in enumerate(data):
            if isinstance(v, str | dict | list | tuple | float):
                found = nul_at(v, (*where, str(i)))
                if found is not None:
                    return found
    return None


# What the NUL check accepts, declared in the schema of every string of a request body (and
# of the names of a body's free-form keys), so the schema says what validation takes.
NO_NUL = "^[^\\x00]*$"


def _declare_no_nul(schema: dict[str, Any]) -> None:
    """Add NO_NUL to each string schema without a pattern, enum or const, in place (nested
    models are declared by their own classes)."""
    if schema.get("type") == "string" and not {"pattern", "enum", "const"} & schema.keys():
        schema["pattern"] = NO_NUL
    for key in ("properties", "patternProperties"):
        for sub in (schema.get(key) or {}).values():
            if isinstance(sub, dict):
                _declare_no_nul(sub)
    for key in ("anyOf", "oneOf", "allOf", "prefixItems"):
        for sub in schema.get(key) or ():
            if isinstance(sub, dict):
                _declare_no_nul(sub)
    for key in ("items", "additionalProperties"):
        if isinstance(schema.get(key), dict):
            _declare_no_nul(schema[key])


def _body_schema(schema: dict[str, Any]) -> None:
    _declare_no_nul(schema)
    if "additionalProperties" not in schema:
        # A body's unknown fields are ignored, not taken (and a NUL in one is still refused):
        # the schema declares none.
        schema["additionalProperties"] = False
    elif schema["additionalProperties"] is not False:
        schema["propertyNames"] = {"pattern": NO_NUL}


class RequestBody(BaseModel):
    """A request body. PostgreSQL text cannot hold a NUL character, so one anywhere in the
    body is a 422 saying where (audited like any invalid write), never a driver error."""

    model_config = ConfigDict(json_schema_extra=_body_schema)

    # Top-level fields not walked: ones whose text is parsed further and refused there (a
    # forwarder's frames, hex data, where a walk would cost more than the rest of validation).
    nul_unchecked: ClassVar[frozenset[str]] = frozenset()

    @model_validator(mode="before")
    @classmethod
    def _no_nul(cls, data: Any) -> Any:
        skip = cls.nul_unchecked
        if skip and isinstance(data, dict):
            where = nul_at({k: v for k, v in data.items() if k not in skip})
        else:
            where = nul_at(data)
        if where is not None:
            path = ".".join(where).replace("\x00", "\\u0000") or "body"
            path = path.encode("utf-8", "backslashreplace").decode()
            raise ValueError(
                f"{path}: NUL characters (\\u0000), lone surrogates, NaN and Infinity "
                "are not accepted"
            )
        return data


class ErrorBody(BaseModel):
    """Every error: a stable `type` and a human `detail`."""

    type: str
    detail: str


# Row ids (keys, alerts, mutes, webhooks) are INTEGER columns: 32 bits on PostgreSQL. A larger
# number in a path or query is a 422, not a driver error (a 500).
MAX_ID = 2**31 - 1


def errors(*codes: int) -> dict[int | str, dict[str, Any]]:
    """OpenAPI `responses` entries for these error statuses."""
    return {code: {"model": ErrorBody} for code in codes}
