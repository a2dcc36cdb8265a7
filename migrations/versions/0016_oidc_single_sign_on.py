"""single sign-on: the people who sign in, their sessions' grants, the audit log's person

Revision ID: 0016_oidc
Revises: 0015_unit_name
Create Date: 2026-11-26

A person signing in through the OpenID provider is a row of `sso_people` (issuer and subject,
the email and name last given) with a key row of their own, which no request can present; a
session of theirs names them (`person_id`) and holds the role and scope their groups gave at
sign-in (`grants`). The audit log names the person of an entry (`subject`, `email`).
"""

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op
from sqlalchemy.dialects import postgresql

revision: str = "0016_oidc"
down_revision: str | None = "0015_unit_name"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

_JSON = sa.JSON().with_variant(postgresql.JSONB(astext_type=sa.Text()), "postgresql")


def upgrade() -> None:
    op.create_table(
        "sso_people",
        sa.Column("id", sa.Integer(), autoincrement=True, nullable=False),
        sa.Column("issuer", sa.String(length=500), nullable=False),
        sa.Column("subject", sa.String(length=255), nullable=False),
        sa.Column("email", sa.String(length=320), nullable=True),
        sa.Column("name", sa.String(length=200), nullable=True),
        sa.Column("key_id", sa.Integer(), nullable=False),
        sa.Column("created_at", sa.Double(), nullable=False),
        sa.Column("last_login_at", sa.Double(), nullable=False),
        sa.ForeignKeyConstraint(
            ["key_id"],
            ["api_keys.id"],
            name=op.f("fk_sso_people_key_id_api_keys"),
            ondelete="CASCADE",
        ),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_sso_people")),
        sa.UniqueConstraint("issuer", "subject", name=op.f("uq_sso_people_issuer_subject")),
    )
    op.create_index(op.f("ix_sso_people_key_id"), "sso_people", ["key_id"], unique=False)
    with op.batch_alter_table("audit_log") as batch:
        batch.add_column(sa.Column("subject", sa.String(length=255), nullable=True))
        batch.add_column(sa.Column("email", sa.String(length=320), nullable=True))
    with op.batch_alter_table("browser_sessions") as batch:
        batch.add_column(sa.Column("person_id", sa.Integer(), nullable=True))
        batch.add_column(sa.Column("grants", _JSON, nullable=True))
        batch.create_foreign_key(
            batch.f("fk_browser_sessions_person_id_sso_people"),
            "sso_people",
            ["person_id"],
            ["id"],
            ondelete="CASCADE",
        )


def downgrade() -> None:
    with op.batch_alter_table("browser_sessions") as batch:
        batch.drop_constraint(
            batch.f("fk_browser_sessions_person_id_sso_people"), type_="foreignkey"
        )
        batch.drop_column("grants")
        batch.drop_column("person_id")
    with op.batch_alter_table("audit_log") as batch:
        batch.drop_column("email")
        batch.drop_column("subject")
    op.drop_index(op.f("ix_sso_people_key_id"), table_name="sso_people")
    op.drop_table("sso_people")
