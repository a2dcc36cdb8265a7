"""write rate limit shared by every gateway; one-time dashboard login codes

Revision ID: 0011_seclogin
Revises: 0010
Create Date: 2026-11-26

The write rate limit of a key was counted in each process: it is now kept in the database
(`write_budgets` serializes a key's checks, `write_hits` is the sliding window's log), so it
holds across every gateway of one database. `login_codes` holds the one-time codes of the
dashboard's login links (SHA-256, expiry), consumed once, on any gateway.
"""

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0011_seclogin"
down_revision: str | None = "0010"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    op.create_table(
        "write_budgets",
        sa.Column("key_id", sa.Integer(), autoincrement=False, nullable=False),
        sa.Column("checked_at", sa.Double(), nullable=False),
        sa.ForeignKeyConstraint(
            ["key_id"],
            ["api_keys.id"],
            name=op.f("fk_write_budgets_key_id_api_keys"),
            ondelete="CASCADE",
        ),
        sa.PrimaryKeyConstraint("key_id", name=op.f("pk_write_budgets")),
    )
    op.create_table(
        "write_hits",
        sa.Column("id", sa.Integer(), autoincrement=True, nullable=False),
        sa.Column("key_id", sa.Integer(), nullable=False),
        sa.Column("ts", sa.Double(), nullable=False),
        sa.ForeignKeyConstraint(
            ["key_id"],
            ["api_keys.id"],
            name=op.f("fk_write_hits_key_id_api_keys"),
            ondelete="CASCADE",
        ),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_write_hits")),
    )
    op.create_index(op.f("ix_write_hits_key_id_write_hits_ts"), "write_hits", ["key_id", "ts"], unique=False)
    op.create_index(op.f("ix_write_hits_ts"), "write_hits", ["ts"], unique=False)
    op.create_table(
        "login_codes",
        sa.Column("id", sa.Integer(), autoincrement=True, nullable=False),
        sa.Column("code_hash", sa.String(length=64), nullable=False),
        sa.Column("key_id", sa.Integer(), nullable=False),
        sa.Column("created_at", sa.Double(), nullable=False),
        sa.Column("expires_at", sa.Double(), nullable=False),
        sa.ForeignKeyConstraint(
            ["key_id"],
            ["api_keys.id"],
            name=op.f("fk_login_codes_key_id_api_keys"),
            ondelete="CASCADE",
        ),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_login_codes")),
        sa.UniqueConstraint("code_hash", name=op.f("uq_login_codes_code_hash")),
    )
    op.create_index(op.f("ix_login_codes_key_id"), "login_codes", ["key_id"], unique=False)
    op.create_index(op.f("ix_login_codes_expires_at"), "login_codes", ["expires_at"], unique=False)


def downgrade() -> None:
    op.drop_index(op.f("ix_login_codes_expires_at"), table_name="login_codes")
    op.drop_index(op.f("ix_login_codes_key_id"), table_name="login_codes")
    op.drop_table("login_codes")
    op.drop_index(op.f("ix_write_hits_ts"), table_name="write_hits")
    op.drop_index(op.f("ix_write_hits_key_id_write_hits_ts"), table_name="write_hits")
    op.drop_table("write_hits")
    op.drop_table("write_budgets")
