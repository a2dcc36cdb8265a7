"""rollups: one row per unit, width and bucket, every metric's aggregate in columns of its own

Revision ID: 0019_rollup_rows
Revises: 0018_partitions
Create Date: 2026-11-27

A row per metric and bucket cost about 100 bytes on PostgreSQL (tuple header, key, index
entry) for 32 bytes of aggregate, 13 rows a minute per unit. Each bucket's metrics move into
one row: `<metric>_n`, `_sum`, `_min`, `_max`, null where the bucket had no value of the
metric. Every existing row is copied (a bucket's rows grouped into one), in one statement, on
both engines; on PostgreSQL the old table and its partitions move aside into a schema of
their own first, and the new table gets the same LIST and RANGE partitions (a partition for
each span that holds rows, the partition keeper makes the others). The downgrade splits the
rows back into a row per metric. A metric the gateway never writes (none outside the list
below) stops the upgrade, with nothing changed, rather than being dropped.
"""

from collections.abc import Callable, Sequence

import sqlalchemy as sa
from alembic import op
from sqlalchemy import Connection, text

from eqgw.store.engine import db_deadline
from eqgw.store.partitions import (
    ORIGIN_S,
    Series,
    create_default,
    is_partitioned,
    make_partition,
    partition_schema,
)

revision: str = "0019_rollup_rows"
down_revision: str | None = "0018_partitions"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

_DAY = 86400
_WEEK = 7 * _DAY
# Frozen as of this revision (not the live registry).
ROLLUP_SPANS: dict[int, int] = {60: _DAY, 900: _WEEK, 3600: 8 * _WEEK, 86400: 52 * _WEEK}
METRICS: tuple[str, ...] = (
    "v12", "v24", "i12", "i24",
    "soc_12v", "soc_24v", "soc",
    "soc_achievable_12v", "soc_achievable_24v", "soc_achievable",
    "soh_12v", "soh_24v", "soh",
    "dod_12v", "dod_24v", "dod",
    "temperature_c",
)  # fmt: skip
_KEY = ("unit_id", "bucket_s", "bucket_ts")
_NARROW = ("unit_id", "metric", "bucket_s", "bucket_ts", "count", "sum", "min", "max")


def _q(name: str) -> str:
    return '"' + name.replace('"', '""') + '"'


def _wide(md: sa.MetaData, name: str, partitioned: bool) -> sa.Table:
    """`rollups` as this revision makes it: the counts first, then the doubles."""
    counts = [sa.Column(f"{m}_n", sa.Integer) for m in METRICS]
    values = [sa.Column(f"{m}_{p}", sa.Double) for m in METRICS for p in ("sum", "min", "max")]
    return sa.Table(
        name,
        md,
        sa.Column("unit_id", sa.Integer, nullable=False),
        sa.Column("bucket_s", sa.Integer, nullable=False),
        sa.Column("bucket_ts", sa.Double, nullable=False),
        *counts,
        *values,
        sa.PrimaryKeyConstraint(*_KEY, name="pk_rollups"),
        sqlite_with_rowid=False,
        **({"postgresql_partition_by": "LIST (bucket_s)"} if partitioned else {}),
    )


def _narrow(md: sa.MetaData, name: str, partitioned: bool) -> sa.Table:
    """`rollups` as 0018 had it: a row per metric and bucket."""
    return sa.Table(
        name,
        md,
        sa.Column("unit_id", sa.Integer, nullable=False),
        sa.Column("metric", sa.String(32), nullable=False),
        sa.Column("bucket_s", sa.Integer, nullable=False),
        sa.Column("bucket_ts", sa.Double, nullable=False),
        sa.Column("count", sa.BigInteger, nullable=False),
        sa.Column("sum", sa.Double, nullable=False),
        sa.Column("min", sa.Double, nullable=False),
        sa.Column("max", sa.Double, nullable=False),
        sa.PrimaryKeyConstraint("unit_id", "metric", "bucket_s", "bucket_ts", name="pk_rollups"),
        sqlite_with_rowid=False,
        **({"postgresql_partition_by": "LIST (bucket_s)"} if partitioned else {}),
    )


def _to_wide(old: str) -> str:
    """The rows of the narrow table `old` grouped into a row per bucket."""
    pick = [f"max(CASE WHEN metric = '{m}' THEN count END)" for m in METRICS] + [
        f"max(CASE WHEN metric = '{m}' THEN {src} END)"
        for m in METRICS
        for src in ("sum", "min", "max")
    ]
    return (
        f"SELECT unit_id, bucket_s, bucket_ts, {', '.join(pick)} FROM {old} "
        "GROUP BY unit_id, bucket_s, bucket_ts"
    )


def _to_narrow(old: str) -> str:
    """The rows of the wide table `old`, a row per metric with a count."""
    return " UNION ALL ".join(
        f"SELECT unit_id, '{m}', bucket_s, bucket_ts, {m}_n, {m}_sum, {m}_min, {m}_max "
        f"FROM {old} WHERE {m}_n IS NOT NULL"
        for m in METRICS
    )


def upgrade() -> None:
    conn = op.get_bind()
    known = ", ".join(f"'{m}'" for m in METRICS)
    unknown = list(
        conn.execute(text(f"SELECT DISTINCT metric FROM rollups WHERE metric NOT IN ({known})"))
        .scalars()
        .all()
    )
    if unknown:
        raise RuntimeError(
            f"rollups hold metrics this version has no columns for: {', '.join(unknown)}; "
            "nothing was changed"
        )
    _rebuild(conn, _wide, _to_wide)


def downgrade() -> None:
    _rebuild(op.get_bind(), _narrow, _to_narrow)


def _rebuild(
    conn: Connection,
    shape: Callable[[sa.MetaData, str, bool], sa.Table],
    rows_of: Callable[[str], str],
) -> None:
    """Replace `rollups` by a table of `shape` holding `rows_of(the old table)`."""
    if conn.dialect.name != "postgresql":
        conn.execute(text("ALTER TABLE rollups RENAME TO rollups_old"))
        new = shape(sa.MetaData(), "rollups_new", False)
        new.create(conn)
        conn.execute(text(f"INSERT INTO rollups_new {rows_of('rollups_old')}"))
        conn.execute(text("DROP TABLE rollups_old"))
        conn.execute(text("ALTER TABLE rollups_new RENAME TO rollups"))
        return
    # Whatever ran it (alembic's own command too): a big table's copy has no deadline.
    with db_deadline(None):
        conn.execute(text("SET LOCAL statement_timeout = 0"))
        _rebuild_pg(conn, shape, rows_of)


def _rebuild_pg(
    conn: Connection,
    shape: Callable[[sa.MetaData, str, bool], sa.Table],
    rows_of: Callable[[str], str],
) -> None:
    schema = conn.execute(text("SELECT current_schema()")).scalar_one()
    aside = f"{schema}_rollups_old"
    partitioned = is_partitioned(conn, "rollups")
    # The old table and every partition of it (their indexes go with them) out of the way:
    # the new ones take the same names.
    tree = conn.execute(
        text(
            "SELECT n.nspname, c.relname FROM pg_partition_tree(to_regclass(:t)) p "
            "JOIN pg_class c ON c.oid = p.relid JOIN pg_namespace n ON n.oid = c.relnamespace"
        ),
        {"t": f"{_q(schema)}.rollups"},
    ).all() or [(schema, "rollups")]
    conn.execute(text(f"CREATE SCHEMA {_q(aside)}"))
    for nsp, rel in tree:
        conn.execute(text(f"ALTER TABLE {_q(nsp)}.{_q(rel)} SET SCHEMA {_q(aside)}"))
    old = f"{_q(aside)}.rollups"
    shape(sa.MetaData(), "rollups", partitioned).create(conn)
    if partitioned:
        parts = partition_schema(conn)
        create_default(conn, Series("rollups", "bucket_ts", _DAY))
        for width, span in ROLLUP_SPANS.items():
            series = Series(f"rollups_{width}", "bucket_ts", span, nested=True)
            conn.execute(
                text(
                    f"CREATE TABLE {_q(parts)}.{_q(series.table)} PARTITION OF rollups "
                    f"FOR VALUES IN ({width}) PARTITION BY RANGE (bucket_ts)"
                )
            )
            create_default(conn, series)
            spans = conn.execute(
                text(
                    f"SELECT DISTINCT floor((bucket_ts - {ORIGIN_S}) / {span}) FROM {old} "
                    "WHERE bucket_s = :w"
                ),
                {"w": width},
            ).scalars()
            for n in sorted(spans):
                lo = ORIGIN_S + float(n) * span
                make_partition(conn, series, lo, lo + span, wait_ms=None)
    conn.execute(text(f"INSERT INTO rollups {rows_of(old)}"))
    conn.execute(text(f"DROP TABLE {old} CASCADE"))
    conn.execute(text(f"DROP SCHEMA {_q(aside)}"))
