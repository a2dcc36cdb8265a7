"""measurements and battery states packed per unit and hour into compressed blocks

Revision ID: 0017_packed_series
Revises: 0014_vehicles_db
Create Date: 2026-12-03

A `measurements` row cost about 90 bytes on PostgreSQL and a `battery_states` row about 130,
for 16-bit fields on the bus. Hours that ended an hour before both the clock and the unit's
newest data move into `measurement_blocks` / `battery_blocks`: a unit's rows of one hour in
one row, packed column by column and compressed (eqgw.store.packed); the newer rows stay as
they are, and the gateway packs them as they age. The tables are read in key order and
written an hour of a unit at a time, so memory holds one batch of blocks whatever their size.
The downgrade unpacks every block back into its table.
"""

import math
import time
from collections.abc import Iterator, Sequence
from typing import Any

import sqlalchemy as sa
from alembic import op

from eqgw.store.packed import PACK_AFTER_S, Series, block_start, pack_rows, series_of, unpack_rows

revision: str = "0017_packed_series"
down_revision: str | None = "0014_vehicles_db"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

# Rows fetched from the server at a time, and blocks (or rows) written per statement.
_FETCH = 50_000
_WRITE = 500
_ROWS_WRITE = 20_000


def _tables() -> list[Series]:
    """The tables as this revision has them (not as the models may have them later)."""
    md = sa.MetaData()

    def blocks(name: str) -> sa.Table:
        return sa.Table(
            name,
            md,
            sa.Column("unit_id", sa.Integer(), primary_key=True, autoincrement=False),
            sa.Column("ts", sa.Double(), primary_key=True),
            sa.Column("samples", sa.Integer()),
            sa.Column("data", sa.LargeBinary()),
        )

    measurements = sa.Table(
        "measurements",
        md,
        sa.Column("unit_id", sa.Integer(), primary_key=True, autoincrement=False),
        sa.Column("ts", sa.Double(), primary_key=True),
        *(sa.Column(c, sa.Double()) for c in ("v12", "v24", "i12", "i24")),
    )
    battery = sa.Table(
        "battery_states",
        md,
        sa.Column("unit_id", sa.Integer(), primary_key=True, autoincrement=False),
        sa.Column("ts", sa.Double(), primary_key=True),
        sa.Column("idx", sa.Integer(), primary_key=True, autoincrement=False),
        sa.Column("battery", sa.String(8)),
        *(
            sa.Column(c, sa.Double())
            for c in ("soc", "soc_achievable", "soh", "dod", "runtime_min", "runtime_temp_adj_min")
        ),
        *(sa.Column(c, sa.Integer()) for c in ("major_12v", "minor_12v", "major_24v", "minor_24v")),
        sa.Column("temperature_c", sa.Double()),
        sa.Column("temperature_raw", sa.Integer()),
    )
    return [
        series_of(measurements, blocks("measurement_blocks")),
        series_of(battery, blocks("battery_blocks")),
    ]


def upgrade() -> None:
    conn = op.get_bind()
    for s in _tables():
        name = s.blocks.name
        op.create_table(
            name,
            sa.Column("unit_id", sa.Integer(), autoincrement=False, nullable=False),
            sa.Column("ts", sa.Double(), nullable=False),
            sa.Column("samples", sa.Integer(), nullable=False),
            sa.Column("data", sa.LargeBinary(), nullable=False),
            sa.PrimaryKeyConstraint("unit_id", "ts", name=op.f(f"pk_{name}")),
        )
        if conn.dialect.name == "postgresql":
            # zlib output does not compress again: no pglz attempt before going out of line.
            op.execute(f"ALTER TABLE {name} ALTER COLUMN data SET STORAGE EXTERNAL")
    edges = _edges(conn, time.time())
    if not edges:
        return
    for s in _tables():
        _pack_table(conn, s, edges)


def _edges(conn: Any, now: float) -> dict[int, float]:
    """Per unit, the block start before which its rows are packed (as eqgw.store.packed)."""
    out: dict[int, float] = {}
    for uid, last in conn.execute(sa.text("SELECT id, last_seen FROM units")):
        if last is not None:
            edge = block_start(min(now, float(last)) - PACK_AFTER_S)
            if math.isfinite(edge):
                out[int(uid)] = edge
    return out


def _pack_table(conn: Any, s: Series, edges: dict[int, float]) -> None:
    cols = ", ".join(s.columns)
    order = ", ".join(s.columns[i] for i in s.key)
    rows = conn.execute(
        sa.text(f"SELECT unit_id, {cols} FROM {s.name} WHERE ts < :top ORDER BY unit_id, {order}"),
        {"top": max(edges.values())},
        execution_options={"yield_per": _FETCH},
    )
    batch: list[dict[str, Any]] = []
    for (uid, start), values in _hours(rows, edges):
        batch.append(
            {"unit_id": uid, "ts": start, "samples": len(values), "data": pack_rows(s, values)}
        )
        if len(batch) >= _WRITE:
            conn.execute(s.blocks.insert(), batch)
            batch = []
    if batch:
        conn.execute(s.blocks.insert(), batch)
    rows.close()  # PostgreSQL: the server-side cursor, before the rows are deleted
    conn.execute(
        sa.text(f"DELETE FROM {s.name} WHERE unit_id = :u AND ts < :e"),
        [{"u": u, "e": e} for u, e in edges.items()],
    )


def _hours(rows: Any, edges: dict[int, float]) -> Iterator[tuple[tuple[int, float], list[Any]]]:
    """Rows in key order, those older than their unit's edge, grouped by unit and block."""
    key: tuple[int, float] | None = None
    values: list[Any] = []
    for row in rows:
        uid, ts = row[0], row[1]
        if ts >= edges.get(uid, -math.inf):
            continue
        k = (uid, block_start(ts))
        if k != key:
            if key is not None:
                yield key, values
            key, values = k, []
        values.append(tuple(row[1:]))
    if key is not None:
        yield key, values


def downgrade() -> None:
    conn = op.get_bind()
    for s in _tables():
        cols = ", ".join(s.columns)
        marks = ", ".join(f":{c}" for c in s.columns)
        # A row both packed and in its table (two gateways racing) is inserted once.
        insert = sa.text(
            f"INSERT INTO {s.name} (unit_id, {cols}) VALUES (:unit_id, {marks}) "
            "ON CONFLICT DO NOTHING"
        )
        blocks = conn.execute(
            sa.text(f"SELECT unit_id, data FROM {s.blocks.name} ORDER BY unit_id, ts"),
            execution_options={"yield_per": 100},
        )
        batch: list[dict[str, Any]] = []
        for uid, data in blocks:
            for values in unpack_rows(s, bytes(data)):
                batch.append({"unit_id": uid, **dict(zip(s.columns, values, strict=True))})
            if len(batch) >= _ROWS_WRITE:
                conn.execute(insert, batch)
                batch = []
        if batch:
            conn.execute(insert, batch)
        blocks.close()
        op.drop_table(s.blocks.name)
