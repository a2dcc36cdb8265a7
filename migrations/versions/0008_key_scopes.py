"""key scopes, expiry and rotation

Revision ID: 0008
Revises: 0007
Create Date: 2026-11-24

An API key's scope (the depots and vehicles it may see and command; none: the whole fleet),
its optional expiry, and its lineage: the id of the first key of a chain of rotations, which
owns the forwarder streams an ingest key uploaded (so a rotated key continues them).
"""

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op
from sqlalchemy.dialects import postgresql

revision: str = "0008"
down_revision: str | None = "0007"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

_JSON = sa.JSON().with_variant(postgresql.JSONB(astext_type=sa.Text()), "postgresql")


def upgrade() -> None:
    with op.batch_alter_table("api_keys") as batch:
        batch.add_column(sa.Column("scope_groups", _JSON, nullable=True))
        batch.add_column(sa.Column("scope_vehicles", _JSON, nullable=True))
        batch.add_column(sa.Column("expires_at", sa.Double(), nullable=True))
        batch.add_column(sa.Column("lineage", sa.Integer(), nullable=True))


def downgrade() -> None:
    with op.batch_alter_table("api_keys") as batch:
        batch.drop_column("lineage")
        batch.drop_column("expires_at")
        batch.drop_column("scope_vehicles")
        batch.drop_column("scope_groups")
