"""One line naming an exception, for status pages, logs and command-line messages."""

from __future__ import annotations


def describe(exc: BaseException) -> str:
    """`Type: first line of the message`, at most 300 characters. python-can's socketcand
    errors embed a whole traceback after the first line, SQLAlchemy's its SQL and a link."""
    text = str(exc).strip().splitlines()
    first = text[0] if text else ""
    line = f"{type(exc).__name__}: {first}" if first else type(exc).__name__
    return line if len(line) <= 300 else line[:297] + "..."
