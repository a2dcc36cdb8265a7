"""Looking into a database a gateway process owns: one statement on a short-lived engine."""

from __future__ import annotations

from typing import Any

from sqlalchemy import Row, text

from eqgw.store.engine import create_engine


def query(url: str, sql: str, **params: Any) -> list[Row[Any]]:
    """Every row of one SQL statement, on an engine of its own disposed at once."""
    engine = create_engine(url)
    try:
        with engine.connect() as conn:
            return list(conn.execute(text(sql), params).all())
    finally:
        engine.dispose()
