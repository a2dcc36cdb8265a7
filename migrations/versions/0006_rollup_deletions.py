"""rollup deletion generations

Revision ID: 0006
Revises: 0005
Create Date: 2026-11-24

Per unit, a counter the retention bumps in the transaction of each rollup deletion: the
history cache checks it, so a bucket deleted and written again with the same sample count
(a late frame after the retention) is never served from what was cached before.
"""

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0006"
down_revision: str | None = "0005"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    op.create_table(
        "rollup_deletions",
        sa.Column("unit_id", sa.Integer(), autoincrement=False, nullable=False),
        sa.Column("generation", sa.BigInteger(), nullable=False),
        sa.Column("last_at", sa.Double(), nullable=False),
        sa.PrimaryKeyConstraint("unit_id", name=op.f("pk_rollup_deletions")),
    )


def downgrade() -> None:
    op.drop_table("rollup_deletions")
