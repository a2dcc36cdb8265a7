"""Looking into a database a gateway process owns: one statement on a short-lived engine."""

from __future__ import annotations

from typing import Any, NamedTuple

from sqlalchemy import Connection, Row, text

from eqgw.store import archive
from eqgw.store.engine import create_engine


def query(url: str, sql: str, **params: Any) -> list[Row[Any]]:
    """Every row of one SQL statement, on an engine of its own disposed at once."""
    engine = create_engine(url)
    try:
        with engine.connect() as conn:
            return list(conn.execute(text(sql), params).all())
    finally:
        engine.dispose()


class ArchivedFrame(NamedTuple):
    """A frame of the raw archive with its unit's bus (the bare identifier in `can_id`)."""

    bus: str
    ts: float
    can_id: int
    seq: int
    data: bytes


def archived_in(conn: Connection) -> list[ArchivedFrame]:
    """Every frame of the raw archive (packed or not yet), in time order."""
    buses = {int(i): str(b) for i, b in conn.execute(text("SELECT id, bus FROM units"))}
    return [
        ArchivedFrame(buses[u], f.ts, f.can_id, f.seq, f.data)
        for u, f in archive.read_frames(conn, sorted(buses))
    ]


def archived_frames(url: str) -> list[ArchivedFrame]:
    """Every frame of the raw archive of the database at `url`, on an engine of its own."""
    engine = create_engine(url)
    try:
        with engine.connect() as conn:
            return archived_in(conn)
    finally:
        engine.dispose()
