"""webhooks, their outbox and delivery log

Revision ID: 0004
Revises: 0003
Create Date: 2026-11-23

Alert delivery (issue 7): webhook endpoints, the persistent outbox and the delivery log.
"""

from collections.abc import Sequence

revision: str = "0004"
down_revision: str | None = "0003"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    pass


def downgrade() -> None:
    pass
