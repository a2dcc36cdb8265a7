"""raw frames keyed by their place among frames sharing a timestamp

Revision ID: 0007
Revises: 0006
Create Date: 2026-11-24

`raw_frames` was keyed (unit, ts, can_id): frames of one id stamped alike (a log's timestamp
resolution, several frames of one record) collapsed into one row. A `seq` column, the frame's
index among the unit's frames with that id and timestamp, joins the key; existing rows get 0.
"""

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0007"
down_revision: str | None = "0006"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    # SQLite: the table is rebuilt (batch mode), still clustered on its key (WITHOUT ROWID).
    with op.batch_alter_table(
        "raw_frames", recreate="auto", table_kwargs={"sqlite_with_rowid": False}
    ) as batch:
        batch.add_column(
            sa.Column(
                "seq",
                sa.SmallInteger(),
                autoincrement=False,
                nullable=False,
                server_default=sa.text("0"),
            )
        )
        batch.drop_constraint("pk_raw_frames", type_="primary")
        batch.create_primary_key("pk_raw_frames", ["unit_id", "ts", "can_id", "seq"])


def downgrade() -> None:
    # Frames beyond the first of a key have no place in the old key: they are dropped.
    op.execute("DELETE FROM raw_frames WHERE seq > 0")
    with op.batch_alter_table(
        "raw_frames", recreate="auto", table_kwargs={"sqlite_with_rowid": False}
    ) as batch:
        batch.drop_constraint("pk_raw_frames", type_="primary")
        batch.create_primary_key("pk_raw_frames", ["unit_id", "ts", "can_id"])
        batch.drop_column("seq")
