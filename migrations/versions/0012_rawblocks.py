"""raw frames packed per unit and minute into compressed blocks

Revision ID: 0012_rawblocks
Revises: 0016_oidc
Create Date: 2026-11-28

`raw_frames` kept a row per frame (about 132 bytes each on PostgreSQL with its index). The
raw archive becomes `raw_blocks`, a unit's frames of one minute packed and compressed in one
row (eqgw.store.archive), and `raw_recent`, the frames of the minutes not packed yet, a row
each as before. Every stored frame moves into its block: `raw_frames` is read in key order and
written a minute of a unit at a time, so memory holds one batch of blocks, whatever the table's
size. The stored frames were all extended data frames (the only ones the ingest archives).
The downgrade unpacks every block back into `raw_frames`.
"""

from collections.abc import Iterator, Sequence
from typing import Any

import sqlalchemy as sa
from alembic import op

from eqgw.store.archive import (
    CAN_EFF_FLAG,
    CAN_EFF_MASK,
    Frame,
    block_start,
    pack_block,
    unpack_block,
)

revision: str = "0012_rawblocks"
down_revision: str | None = "0016_oidc"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

# Rows fetched from the server at a time, and blocks (or rows) written per statement.
_FETCH = 50_000
_WRITE = 2_000


def upgrade() -> None:
    op.create_table(
        "raw_blocks",
        sa.Column("unit_id", sa.Integer(), autoincrement=False, nullable=False),
        sa.Column("ts", sa.Double(), nullable=False),
        sa.Column("frames", sa.Integer(), nullable=False),
        sa.Column("data", sa.LargeBinary(), nullable=False),
        sa.PrimaryKeyConstraint("unit_id", "ts", name=op.f("pk_raw_blocks")),
    )
    _create_frame_table("raw_recent")
    conn = op.get_bind()
    blocks = sa.table(
        "raw_blocks",
        sa.column("unit_id", sa.Integer()),
        sa.column("ts", sa.Double()),
        sa.column("frames", sa.Integer()),
        sa.column("data", sa.LargeBinary()),
    )
    rows = conn.execute(
        sa.text("SELECT unit_id, ts, can_id, seq, data FROM raw_frames ORDER BY unit_id, ts"),
        execution_options={"yield_per": _FETCH},
    )
    batch: list[dict[str, Any]] = []
    for (uid, start), frames in _minutes(rows):
        batch.append({"unit_id": uid, "ts": start, "frames": len(frames), "data": pack_block(frames)})
        if len(batch) >= _WRITE:
            conn.execute(blocks.insert(), batch)
            batch = []
    if batch:
        conn.execute(blocks.insert(), batch)
    rows.close()  # PostgreSQL: the server-side cursor, before its table is dropped
    op.drop_table("raw_frames")


def _minutes(rows: Any) -> Iterator[tuple[tuple[int, float], list[Frame]]]:
    """Rows in (unit, ts) order grouped by unit and block."""
    key: tuple[int, float] | None = None
    frames: list[Frame] = []
    for uid, ts, can_id, seq, data in rows:
        k = (uid, block_start(ts))
        if k != key:
            if key is not None:
                yield key, frames
            key, frames = k, []
        frames.append(Frame(ts, (can_id & CAN_EFF_MASK) | CAN_EFF_FLAG, seq, bytes(data)))
    if key is not None:
        yield key, frames


def _create_frame_table(name: str) -> None:
    op.create_table(
        name,
        sa.Column("unit_id", sa.Integer(), autoincrement=False, nullable=False),
        sa.Column("ts", sa.Double(), nullable=False),
        sa.Column("can_id", sa.BigInteger(), nullable=False),
        sa.Column(
            "seq", sa.SmallInteger(), server_default=sa.text("0"), autoincrement=False,
            nullable=False,
        ),
        sa.Column("data", sa.LargeBinary(), nullable=False),
        sa.PrimaryKeyConstraint("unit_id", "ts", "can_id", "seq", name=op.f(f"pk_{name}")),
        sqlite_with_rowid=False,
    )  # fmt: skip


def downgrade() -> None:
    # Frames other than extended data frames have no place in raw_frames: none is archived.
    _create_frame_table("raw_frames")
    conn = op.get_bind()
    # A frame both packed and waiting (two gateways racing) is inserted once.
    insert = sa.text(
        "INSERT INTO raw_frames (unit_id, ts, can_id, seq, data) "
        "VALUES (:unit_id, :ts, :can_id, :seq, :data) ON CONFLICT DO NOTHING"
    ).bindparams(sa.bindparam("data", type_=sa.LargeBinary()))
    batch: list[dict[str, Any]] = []

    def add(uid: int, f: Frame) -> None:
        nonlocal batch
        if f.word & ~(CAN_EFF_FLAG | CAN_EFF_MASK) or not f.word & CAN_EFF_FLAG:
            return
        batch.append(
            {"unit_id": uid, "ts": f.ts, "can_id": f.word & CAN_EFF_MASK, "seq": f.seq,
             "data": f.data}
        )  # fmt: skip
        if len(batch) >= _WRITE * 10:
            conn.execute(insert, batch)
            batch = []

    blocks = conn.execute(
        sa.text("SELECT unit_id, data FROM raw_blocks ORDER BY unit_id, ts"),
        execution_options={"yield_per": 1000},
    )
    for uid, data in blocks:
        for f in unpack_block(bytes(data)):
            add(uid, f)
    blocks.close()
    recent = conn.execute(
        sa.text("SELECT unit_id, ts, can_id, seq, data FROM raw_recent"),
        execution_options={"yield_per": _FETCH},
    )
    for uid, ts, word, seq, data in recent:
        add(uid, Frame(ts, word, seq, bytes(data)))
    recent.close()
    if batch:
        conn.execute(insert, batch)
    op.drop_table("raw_recent")
    op.drop_table("raw_blocks")
