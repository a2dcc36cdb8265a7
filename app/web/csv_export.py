"""CSV answers streamed page by page (the domains' exports: fault episodes, alerts, the
audit log, each a `Page` of its own rows).

A range of any size is answered without holding it: the rows are read in keyset pages of
`PAGE` (id above the last one sent, in id order), each page in its own short transaction in a
worker thread, within a database deadline of its own (`Runtime.db_page`: a long export is not
cut part-way), turned into CSV there and sent before the next is read. Memory is bounded by one
page, whatever the range (docs/api.md gives the figure and the command that measures it).

A failure after the first bytes were sent cannot become an error status any more: the
connection is then closed without the chunked body's end, which every HTTP client reports as an
incomplete answer, so a cut export is never taken for a whole one.
"""

from __future__ import annotations

import csv
import io
from collections.abc import AsyncIterator, Callable, Mapping, Sequence
from typing import Any

from fastapi import Request
from fastapi.responses import StreamingResponse
from sqlalchemy import Connection

from eqgw.web.responses import dumps
from eqgw.web.runtime import Runtime

# Rows read, converted and sent at a time.
PAGE = 1000
MEDIA_TYPE = "text/csv"


# The OpenAPI entry of a CSV answer (a generated client reads it as text).
CSV_CONTENT = {MEDIA_TYPE: {"schema": {"type": "string"}}}
# Cells that a spreadsheet would run as a formula (text that came from clients, such as a
# refused request's detail, could otherwise reach someone's Excel as `=HYPERLINK(...)`).
_FORMULA_START = ("=", "+", "-", "@", "\t", "\r")

Page = Callable[[Connection, int, int], Sequence[Mapping[str, Any]]]


def wants_csv(request: Request, format: str | None) -> bool:
    """`?format=csv`, or no `format` and `Accept` naming text/csv."""
    if format is not None:
        return format == "csv"
    return MEDIA_TYPE in request.headers.get("accept", "")


def _cell(value: Any) -> Any:
    if value is None:
        return ""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, dict | list):
        return dumps(value).decode()
    if isinstance(value, str) and value.startswith(_FORMULA_START):
        return "'" + value
    return value


def _rows_csv(rows: Sequence[Mapping[str, Any]], columns: Sequence[str]) -> bytes:
    buf = io.StringIO()
    csv.writer(buf).writerows([_cell(r.get(c)) for c in columns] for r in rows)
    return buf.getvalue().encode()


async def csv_pages(rt: Runtime, columns: Sequence[str], page: Page) -> AsyncIterator[bytes]:
    """The header, then each page of rows as CSV, read after the previous one was sent."""
    yield _rows_csv([{c: c for c in columns}], columns)
    after = 0
    while True:

        def run(conn: Connection, after: int = after) -> tuple[bytes, int, int]:
            rows = page(conn, after, PAGE)
            return _rows_csv(rows, columns), (rows[-1]["id"] if rows else after), len(rows)

        chunk, after, n = await rt.db_page(run)
        if n:
            yield chunk
        if n < PAGE:
            return


def stream(rt: Runtime, name: str, columns: Sequence[str], page: Page) -> StreamingResponse:
    """A streamed CSV answer, offered for download as `name`.csv."""
    return StreamingResponse(
        csv_pages(rt, columns, page),
        media_type=MEDIA_TYPE,
        headers={"Content-Disposition": f'attachment; filename="{name}.csv"'},
    )
