"""alert rules, alerts and mutes

Revision ID: 0003
Revises: 0002
Create Date: 2026-11-23

Alerting (issue 7): rules, the alerts with their lifecycle, and per-vehicle/per-rule mutes.
"""

from collections.abc import Sequence

revision: str = "0003"
down_revision: str | None = "0002"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    pass


def downgrade() -> None:
    pass
