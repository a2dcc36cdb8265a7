"""initial schema

Revision ID: 0001
Revises:
Create Date: 2026-11-21

Tables for the fleet, units, time series (clustered on their natural keys, WITHOUT ROWID on
SQLite), fault episodes, rollups, live state and the raw-frame archive.
"""

from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op
from sqlalchemy.dialects import postgresql

revision: str = "0001"
down_revision: str | None = None
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None


def upgrade() -> None:
    op.create_table(
        "battery_states",
        sa.Column("unit_id", sa.Integer(), autoincrement=False, nullable=False),
        sa.Column("ts", sa.Double(), nullable=False),
        sa.Column("idx", sa.Integer(), autoincrement=False, nullable=False),
        sa.Column("battery", sa.String(length=8), nullable=True),
        sa.Column("soc", sa.Double(), nullable=True),
        sa.Column("soc_achievable", sa.Double(), nullable=True),
        sa.Column("soh", sa.Double(), nullable=True),
        sa.Column("dod", sa.Double(), nullable=True),
        sa.Column("runtime_min", sa.Double(), nullable=True),
        sa.Column("runtime_temp_adj_min", sa.Double(), nullable=True),
        sa.Column("major_12v", sa.Integer(), nullable=True),
        sa.Column("minor_12v", sa.Integer(), nullable=True),
        sa.Column("major_24v", sa.Integer(), nullable=True),
        sa.Column("minor_24v", sa.Integer(), nullable=True),
        sa.Column("temperature_c", sa.Double(), nullable=True),
        sa.Column("temperature_raw", sa.Integer(), nullable=True),
        sa.PrimaryKeyConstraint("unit_id", "ts", "idx", name=op.f("pk_battery_states")),
        sqlite_with_rowid=False,
    )
    op.create_table(
        "dm1_snapshots",
        sa.Column("unit_id", sa.Integer(), autoincrement=False, nullable=False),
        sa.Column("ts", sa.Double(), nullable=False),
        sa.Column(
            "lamps",
            sa.JSON().with_variant(postgresql.JSONB(astext_type=sa.Text()), "postgresql"),
            nullable=False,
        ),
        sa.Column(
            "dtcs",
            sa.JSON().with_variant(postgresql.JSONB(astext_type=sa.Text()), "postgresql"),
            nullable=False,
        ),
        sa.PrimaryKeyConstraint("unit_id", "ts", name=op.f("pk_dm1_snapshots")),
        sqlite_with_rowid=False,
    )
    op.create_table(
        "measurements",
        sa.Column("unit_id", sa.Integer(), autoincrement=False, nullable=False),
        sa.Column("ts", sa.Double(), nullable=False),
        sa.Column("v12", sa.Double(), nullable=True),
        sa.Column("v24", sa.Double(), nullable=True),
        sa.Column("i12", sa.Double(), nullable=True),
        sa.Column("i24", sa.Double(), nullable=True),
        sa.PrimaryKeyConstraint("unit_id", "ts", name=op.f("pk_measurements")),
        sqlite_with_rowid=False,
    )
    op.create_table(
        "messages",
        sa.Column("unit_id", sa.Integer(), autoincrement=False, nullable=False),
        sa.Column("ts", sa.Double(), nullable=False),
        sa.Column("name", sa.String(length=32), nullable=False),
        sa.Column("idx", sa.Integer(), nullable=False),
        sa.Column(
            "fields",
            sa.JSON().with_variant(postgresql.JSONB(astext_type=sa.Text()), "postgresql"),
            nullable=False,
        ),
        sa.PrimaryKeyConstraint("unit_id", "ts", "name", "idx", name=op.f("pk_messages")),
        sqlite_with_rowid=False,
    )
    op.create_table(
        "raw_frames",
        sa.Column("unit_id", sa.Integer(), autoincrement=False, nullable=False),
        sa.Column("ts", sa.Double(), nullable=False),
        sa.Column("can_id", sa.BigInteger(), nullable=False),
        sa.Column("data", sa.LargeBinary(), nullable=False),
        sa.PrimaryKeyConstraint("unit_id", "ts", "can_id", name=op.f("pk_raw_frames")),
        sqlite_with_rowid=False,
    )
    op.create_table(
        "rollups",
        sa.Column("unit_id", sa.Integer(), autoincrement=False, nullable=False),
        sa.Column("metric", sa.String(length=32), nullable=False),
        sa.Column("bucket_s", sa.Integer(), autoincrement=False, nullable=False),
        sa.Column("bucket_ts", sa.Double(), nullable=False),
        sa.Column("count", sa.BigInteger(), nullable=False),
        sa.Column("sum", sa.Double(), nullable=False),
        sa.Column("min", sa.Double(), nullable=False),
        sa.Column("max", sa.Double(), nullable=False),
        sa.PrimaryKeyConstraint(
            "unit_id", "metric", "bucket_s", "bucket_ts", name=op.f("pk_rollups")
        ),
        sqlite_with_rowid=False,
    )
    op.create_table(
        "status_changes",
        sa.Column("unit_id", sa.Integer(), autoincrement=False, nullable=False),
        sa.Column("ts", sa.Double(), nullable=False),
        sa.Column(
            "flags",
            sa.JSON().with_variant(postgresql.JSONB(astext_type=sa.Text()), "postgresql"),
            nullable=False,
        ),
        sa.Column(
            "changed",
            sa.JSON().with_variant(postgresql.JSONB(astext_type=sa.Text()), "postgresql"),
            nullable=False,
        ),
        sa.PrimaryKeyConstraint("unit_id", "ts", name=op.f("pk_status_changes")),
        sqlite_with_rowid=False,
    )
    op.create_table(
        "vehicles",
        sa.Column("id", sa.String(length=64), nullable=False),
        sa.Column("name", sa.String(length=200), nullable=False),
        sa.Column("depot", sa.String(length=200), nullable=True),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_vehicles")),
    )
    op.create_table(
        "units",
        sa.Column("id", sa.Integer(), autoincrement=True, nullable=False),
        sa.Column("vehicle_id", sa.String(length=64), nullable=False),
        sa.Column("bus", sa.String(length=200), nullable=False),
        sa.Column("sa", sa.Integer(), nullable=False),
        sa.Column("series", sa.Integer(), nullable=True),
        sa.Column("model", sa.String(length=64), nullable=True),
        sa.Column("software_id", sa.String(length=64), nullable=True),
        sa.Column("first_seen", sa.Double(), nullable=True),
        sa.Column("last_seen", sa.Double(), nullable=True),
        sa.ForeignKeyConstraint(
            ["vehicle_id"], ["vehicles.id"], name=op.f("fk_units_vehicle_id_vehicles")
        ),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_units")),
        sa.UniqueConstraint("bus", "sa", name=op.f("uq_units_bus_sa")),
    )
    with op.batch_alter_table("units", schema=None) as batch_op:
        batch_op.create_index(batch_op.f("ix_units_vehicle_id"), ["vehicle_id"], unique=False)

    op.create_table(
        "fault_episodes",
        sa.Column("id", sa.Integer(), autoincrement=True, nullable=False),
        sa.Column("unit_id", sa.Integer(), nullable=False),
        sa.Column("fault", sa.String(length=64), nullable=False),
        sa.Column("spn", sa.Integer(), nullable=True),
        sa.Column("fmi", sa.Integer(), nullable=True),
        sa.Column("source", sa.String(length=32), nullable=False),
        sa.Column("state", sa.String(length=16), nullable=False),
        sa.Column("started_at", sa.Double(), nullable=False),
        sa.Column("last_seen_at", sa.Double(), nullable=False),
        sa.Column("ended_at", sa.Double(), nullable=True),
        sa.Column("ended_by", sa.String(length=32), nullable=True),
        sa.Column("occurrence_count", sa.Integer(), nullable=True),
        sa.ForeignKeyConstraint(
            ["unit_id"], ["units.id"], name=op.f("fk_fault_episodes_unit_id_units")
        ),
        sa.PrimaryKeyConstraint("id", name=op.f("pk_fault_episodes")),
        sa.UniqueConstraint(
            "unit_id",
            "fault",
            "started_at",
            name=op.f("uq_fault_episodes_unit_id_fault_started_at"),
        ),
    )
    with op.batch_alter_table("fault_episodes", schema=None) as batch_op:
        batch_op.create_index(batch_op.f("ix_fault_episodes_state"), ["state"], unique=False)

    op.create_table(
        "live_state",
        sa.Column("unit_id", sa.Integer(), nullable=False),
        sa.Column("name", sa.String(length=32), nullable=False),
        sa.Column("ts", sa.Double(), nullable=False),
        sa.Column(
            "fields",
            sa.JSON().with_variant(postgresql.JSONB(astext_type=sa.Text()), "postgresql"),
            nullable=False,
        ),
        sa.ForeignKeyConstraint(
            ["unit_id"], ["units.id"], name=op.f("fk_live_state_unit_id_units")
        ),
        sa.PrimaryKeyConstraint("unit_id", "name", name=op.f("pk_live_state")),
    )


def downgrade() -> None:
    op.drop_table("live_state")
    with op.batch_alter_table("fault_episodes", schema=None) as batch_op:
        batch_op.drop_index(batch_op.f("ix_fault_episodes_state"))

    op.drop_table("fault_episodes")
    with op.batch_alter_table("units", schema=None) as batch_op:
        batch_op.drop_index(batch_op.f("ix_units_vehicle_id"))

    op.drop_table("units")
    op.drop_table("vehicles")
    op.drop_table("status_changes")
    op.drop_table("rollups")
    op.drop_table("raw_frames")
    op.drop_table("messages")
    op.drop_table("measurements")
    op.drop_table("dm1_snapshots")
    op.drop_table("battery_states")
