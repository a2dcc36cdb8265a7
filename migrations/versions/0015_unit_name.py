"""a unit is its NAME: units.name and the unit_owners periods

Revision ID: 0015_unit_name
Revises: 0011_seclogin
Create Date: 2026-11-27

`units.name` is the J1939 NAME (hex text) of the node holding the unit's address, from its
address claim; `unit_owners` keeps one row per NAME taking the address (since when), so a
history read can tell which node a period belongs to. Both are filled from the address claims
already stored (`messages` named `address_claim`); units never claimed stay NULL / without
periods.
"""

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op

revision: str = "0015_unit_name"
down_revision: str | None = "0011_seclogin"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    with op.batch_alter_table("units") as batch:
        batch.add_column(sa.Column("name", sa.String(length=18), nullable=True))
    op.create_table(
        "unit_owners",
        sa.Column("unit_id", sa.Integer(), nullable=False),
        sa.Column("since", sa.Double(), nullable=False),
        sa.Column("name", sa.String(length=18), nullable=False),
        sa.ForeignKeyConstraint(
            ["unit_id"], ["units.id"], name=op.f("fk_unit_owners_unit_id_units")
        ),
        sa.PrimaryKeyConstraint("unit_id", "since", name=op.f("pk_unit_owners")),
    )
    json = sa.JSON().with_variant(sa.dialects.postgresql.JSONB(), "postgresql")
    messages = sa.table(
        "messages",
        sa.column("unit_id", sa.Integer()),
        sa.column("ts", sa.Double()),
        sa.column("name", sa.String()),
        sa.column("fields", json),
    )
    conn = op.get_bind()
    rows = conn.execute(
        sa.select(messages.c.unit_id, messages.c.ts, messages.c.fields)
        .where(messages.c.name == "address_claim")
        .order_by(messages.c.unit_id, messages.c.ts)
    )
    owners: list[dict[str, object]] = []
    current: dict[int, str] = {}
    for unit_id, ts, fields in rows:
        name = (fields or {}).get("name")
        if isinstance(name, str) and current.get(unit_id) != name:
            current[unit_id] = name
            owners.append({"unit_id": unit_id, "since": ts, "name": name})
    if owners:
        owner_table = sa.table(
            "unit_owners",
            sa.column("unit_id", sa.Integer()),
            sa.column("since", sa.Double()),
            sa.column("name", sa.String()),
        )
        conn.execute(sa.insert(owner_table), owners)
        units = sa.table("units", sa.column("id", sa.Integer()), sa.column("name", sa.String()))
        conn.execute(
            sa.update(units).where(units.c.id == sa.bindparam("uid")).values(name=sa.bindparam("n")),
            [{"uid": uid, "n": name} for uid, name in current.items()],
        )


def downgrade() -> None:
    op.drop_table("unit_owners")
    with op.batch_alter_table("units") as batch:
        batch.drop_column("name")
