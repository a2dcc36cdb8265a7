"""Types of JSON data: decoded fields, live state, event bodies (what `json.dumps` takes)."""

from __future__ import annotations

from typing import TypeAlias

# A JSON value as Python holds it. Read-only consumers take `JSONObject`; builders of a
# dict of fields annotate it `dict[str, JSONValue]` (dicts are invariant in their values).
JSONValue: TypeAlias = "bool | int | float | str | list[JSONValue] | dict[str, JSONValue] | None"
JSONObject: TypeAlias = "dict[str, JSONValue]"
