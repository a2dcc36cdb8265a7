"""what of a command was handed to an interface, written before it is handed

Revision ID: 0010
Revises: 0009
Create Date: 2026-11-24

`handed_at` is written before the first frame of a command goes to an interface, so a gateway
that dies, or whose database refuses the record, right after a frame left can never have the
command reported as unsent (expired, failed) by its next start or by another gateway.
`frames_handed` counts the frames of sends that did not complete.
"""

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0010"
down_revision: str | None = "0009"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    with op.batch_alter_table("commands") as batch:
        batch.add_column(sa.Column("handed_at", sa.Double(), nullable=True))
        batch.add_column(
            sa.Column("frames_handed", sa.Integer(), nullable=False, server_default=sa.text("0"))
        )
    # A command recorded as sent before this revision was handed over when it was first sent.
    op.execute("UPDATE commands SET handed_at = first_sent_at WHERE first_sent_at IS NOT NULL")


def downgrade() -> None:
    with op.batch_alter_table("commands") as batch:
        batch.drop_column("frames_handed")
        batch.drop_column("handed_at")
