"""the fleet in the database: vehicles' buses, the fleet's version, retired vehicles

Revision ID: 0014_vehicles_db
Revises: 0016_oidc
Create Date: 2026-12-02

Vehicles and their buses are managed in the database (the API and `eqgw vehicles import`);
the fleet file seeds a database that has no fleet yet. `vehicle_buses` holds each vehicle's
buses; `fleet_revision` (one row) the fleet's version, which every change raises and every
gateway polls; a deleted vehicle is retired (`vehicles.retired_at`), its history kept.
"""

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op
from sqlalchemy.dialects import postgresql

revision: str = "0014_vehicles_db"
down_revision: str | None = "0012_rawblocks"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

_JSON = sa.JSON().with_variant(postgresql.JSONB(), "postgresql")


def upgrade() -> None:
    with op.batch_alter_table("vehicles") as batch:
        batch.add_column(sa.Column("retired_at", sa.Double(), nullable=True))
    op.create_table(
        "vehicle_buses",
        sa.Column("name", sa.String(length=200), nullable=False),
        sa.Column("vehicle_id", sa.String(length=64), nullable=False),
        sa.Column("interface", sa.String(length=64), nullable=False),
        sa.Column("channel", sa.String(length=200), nullable=False),
        sa.Column("bitrate", sa.Integer(), nullable=True),
        sa.Column("options", _JSON, nullable=False),
        sa.Column("equalizer_sas", _JSON, nullable=False),
        sa.Column("gateway_sa", sa.Integer(), nullable=False),
        sa.Column("request_byte_order", sa.String(length=8), nullable=False),
        sa.Column("address_claim", sa.Boolean(), nullable=False),
        sa.Column("address_claim_name", sa.String(length=20), nullable=True),
        sa.Column("stall_after_s", sa.Double(), nullable=False),
        sa.Column("updated_at", sa.Double(), nullable=False),
        sa.ForeignKeyConstraint(
            ["vehicle_id"], ["vehicles.id"], name=op.f("fk_vehicle_buses_vehicle_id_vehicles")
        ),
        sa.PrimaryKeyConstraint("name", name=op.f("pk_vehicle_buses")),
    )
    op.create_index(
        op.f("ix_vehicle_buses_vehicle_id"), "vehicle_buses", ["vehicle_id"], unique=False
    )
    op.create_table(
        "fleet_revision",
        sa.Column("id", sa.Integer(), autoincrement=False, nullable=False),
        sa.Column("version", sa.BigInteger(), nullable=False),
        sa.Column("changed_at", sa.Double(), nullable=False),
        sa.Column("seeded_at", sa.Double(), nullable=False),
        sa.Column("seeded_from", sa.String(length=200), nullable=False),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_fleet_revision")),
    )


def downgrade() -> None:
    op.drop_table("fleet_revision")
    op.drop_index(op.f("ix_vehicle_buses_vehicle_id"), table_name="vehicle_buses")
    op.drop_table("vehicle_buses")
    # Not a batch copy on SQLite: `units` refers to `vehicles`, and dropping the old table
    # under rows that refer to it fails with foreign keys on. SQLite drops a column in place
    # since 3.35.
    with op.batch_alter_table("vehicles", recreate="never") as batch:
        batch.drop_column("retired_at")
