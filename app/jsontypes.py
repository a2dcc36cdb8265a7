"""Types of JSON data: decoded fields, live state, event bodies (what `json.dumps` takes)."""

from __future__ import annotations

from typing import TypeAlias

# A JSON value as Python holds it. Read-only consumers take `JSONObject`; builders of a
# dict of fields annotate it `dict[str, JSONValue]` (dicts are invariant in their values).
JSONValue: TypeAlias = "bool | int | float | str | list[JSONValue] | dict[str, JSONValue] | None"
JSONObject: TypeAlias = "dict[str, JSONValue]"


# Narrowing of values read from JSON (a decoded record, a row's JSON column, another gateway's
# message): the value itself when it has the type, else what a missing value gives.


def as_object(value: object) -> JSONObject | None:
    """`value` if it is a JSON object (a dict), else None."""
    return value if isinstance(value, dict) else None


def as_int(value: object) -> int | None:
    """`value` if it is an integer, else None."""
    return value if isinstance(value, int) else None


def as_float(value: object) -> float | None:
    """`value` if it is a number (an int or a float, kept as it is), else None."""
    return value if isinstance(value, int | float) else None


def as_str(value: object) -> str | None:
    """`value` if it is a string, else None."""
    return value if isinstance(value, str) else None
