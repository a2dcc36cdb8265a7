"""SQL of edge forwarding: read and advance a forwarder stream's row (eqgw.store.forward_models)."""

from __future__ import annotations

from typing import Any

from sqlalchemy import Connection, select, update

from eqgw.store.forward_models import ForwardStream
from eqgw.store.models import table_of
from eqgw.store.writes import dialect_insert

_streams = table_of(ForwardStream)


def get_stream(conn: Connection, stream: str) -> dict[str, Any] | None:
    """A stream's row, or None when it never uploaded."""
    row = conn.execute(select(_streams).where(_streams.c.stream == stream)).first()
    return row._asdict() if row is not None else None


def locked_acked_seq(conn: Connection, stream: str) -> int:
    """The stream's acked_seq (0 before its first commit), its row locked until the
    transaction ends (PostgreSQL; a SQLite writer holds the database's write lock anyway)."""
    c = _streams.c
    row = conn.execute(select(c.acked_seq).where(c.stream == stream).with_for_update()).first()
    return int(row[0]) if row is not None else 0


def list_streams(conn: Connection) -> list[dict[str, Any]]:
    """Every stream, most recently heard first."""
    rows = conn.execute(select(_streams).order_by(_streams.c.last_seen.desc()))
    return [r._asdict() for r in rows]


def advance_stream(
    conn: Connection,
    *,
    stream: str,
    vehicle_id: str,
    bus: str,
    key_id: int | None,
    acked_seq: int,
    frames: int,
    dropped: int,
    now: float,
) -> None:
    """Record that the stream is stored up to `acked_seq` (call in the rows' transaction)."""
    c = _streams.c
    result = conn.execute(
        update(_streams)
        .where(c.stream == stream)
        .values(
            acked_seq=acked_seq,
            frames=c.frames + frames,
            dropped=dropped,
            key_id=key_id,
            last_seen=now,
        )
    )
    if result.rowcount:
        return
    conn.execute(
        dialect_insert(conn, _streams),
        {
            "stream": stream,
            "vehicle_id": vehicle_id,
            "bus": bus,
            "key_id": key_id,
            "acked_seq": acked_seq,
            "frames": frames,
            "dropped": dropped,
            "first_seen": now,
            "last_seen": now,
        },
    )
