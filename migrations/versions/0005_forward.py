"""edge forwarding streams

Revision ID: 0005
Revises: 0004
Create Date: 2026-11-23

Edge forwarding (issue 8): per forwarder stream, the vehicle and bus it feeds and the highest
sequence number stored, so acknowledgements mean committed and re-uploads are cheap.
"""

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0005"
down_revision: str | None = "0004"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    op.create_table(
        "forward_streams",
        sa.Column("stream", sa.String(length=64), nullable=False),
        sa.Column("vehicle_id", sa.String(length=64), nullable=False),
        sa.Column("bus", sa.String(length=200), nullable=False),
        sa.Column("key_id", sa.Integer(), nullable=True),
        sa.Column("acked_seq", sa.BigInteger(), nullable=False),
        sa.Column("frames", sa.BigInteger(), nullable=False),
        sa.Column("dropped", sa.BigInteger(), nullable=False),
        sa.Column("first_seen", sa.Double(), nullable=False),
        sa.Column("last_seen", sa.Double(), nullable=False),
        sa.PrimaryKeyConstraint("stream", name=op.f("pk_forward_streams")),
    )


def downgrade() -> None:
    op.drop_table("forward_streams")
