"""time partitions of the time-series tables on PostgreSQL (no-op on SQLite)

Revision ID: 0018_partitions
Revises: 0017_packed_series
Create Date: 2026-11-26

Each time-series table becomes a table partitioned by RANGE on its time column (rollups: by
LIST on the bucket width, each width by RANGE on the bucket time), with a DEFAULT partition;
the partitions live in the schema `<schema>_partitions` (eqgw.store.partitions). No row is
copied for the big tables: the existing table, after a CHECK constraint on its time range
(one scan, no rewrite), is attached as one partition holding every time up to the end of its
newest row's span; the retention drops it whole once that end is past the cutoff. Rollups of
the 1-minute width (nine rows in ten) stay in place the same way; the other widths are copied
into partitions of their own. The downgrade copies every table back into a plain one.
"""

import time
from collections.abc import Sequence

import sqlalchemy as sa
from alembic import op
from sqlalchemy import Connection, text

from eqgw.store.engine import db_deadline
from eqgw.store.partitions import (
    ORIGIN_S,
    Series,
    create_default,
    create_partitioned,
    make_partition,
    partition_schema,
    span_start,
)

revision: str = "0018_partitions"
down_revision: str | None = "0017_packed_series"
branch_labels: str | Sequence[str] | None = None
depends_on: str | Sequence[str] | None = None

_DAY = 86400
_WEEK = 7 * _DAY
# Frozen as of this revision (not the live registry): (table, time column, partition span).
TABLES: list[tuple[str, str, int]] = [
    ("measurements", "ts", _DAY),
    ("battery_states", "ts", _DAY),
    ("status_changes", "ts", _WEEK),
    ("dm1_snapshots", "ts", _WEEK),
    ("messages", "ts", _WEEK),
    ("raw_blocks", "ts", _DAY),
    ("raw_recent", "ts", _DAY),
    ("measurement_blocks", "ts", _DAY),
    ("battery_blocks", "ts", _DAY),
]
ROLLUP_SPANS: dict[int, int] = {60: _DAY, 900: _WEEK, 3600: 8 * _WEEK, 86400: 52 * _WEEK}
# The width whose rows stay in the existing table (attached as a partition, not copied).
IN_PLACE_WIDTH = 60


def _q(name: str) -> str:
    return '"' + name.replace('"', '""') + '"'


def _to_legacy(conn: Connection, table: str, schema: str) -> tuple[str, list[str]]:
    """Rename `table` to <table>_legacy in the partitions' schema; its name and primary key."""
    pk = sa.inspect(conn).get_pk_constraint(table)["constrained_columns"]
    legacy = f"{table}_legacy"
    conn.execute(text(f"ALTER TABLE {_q(table)} RENAME TO {_q(legacy)}"))
    conn.execute(
        text(
            f"ALTER TABLE {_q(legacy)} RENAME CONSTRAINT {_q('pk_' + table)} "
            f"TO {_q(legacy + '_pkey')}"
        )
    )
    conn.execute(text(f"ALTER TABLE {_q(legacy)} SET SCHEMA {_q(schema)}"))
    return f"{_q(schema)}.{_q(legacy)}", pk


def _attach_legacy(
    conn: Connection, parent: str, legacy: str, column: str, span: int, where: str = "TRUE"
) -> None:
    """Attach `legacy` to `parent` as the partition FROM (MINVALUE) TO (the end of its newest
    row's span, at most the end of today's), or drop it when it holds no row. Rows stamped
    after today (a clock that was ahead) go to the default partition first, so that the old
    table does not cover the future. The CHECK constraint proves the range, so ATTACH does
    not scan again."""
    col = _q(column)
    cap = span_start(time.time(), span) + span
    newest = conn.execute(text(f"SELECT max({col}) FROM {legacy}")).scalar_one_or_none()
    if newest is None:
        conn.execute(text(f"DROP TABLE {legacy}"))
        return
    if newest >= cap:
        conn.execute(text(f"INSERT INTO {parent} SELECT * FROM {legacy} WHERE {col} >= {cap!r}"))
        conn.execute(text(f"DELETE FROM {legacy} WHERE {col} >= {cap!r}"))
        newest = conn.execute(text(f"SELECT max({col}) FROM {legacy}")).scalar_one_or_none()
        if newest is None:
            conn.execute(text(f"DROP TABLE {legacy}"))
            return
    hi = span_start(float(newest), span) + span
    conn.execute(
        text(
            f"ALTER TABLE {legacy} ADD CONSTRAINT legacy_range "
            f"CHECK ({where} AND {col} IS NOT NULL AND {col} < {hi!r})"
        )
    )
    conn.execute(
        text(
            f"ALTER TABLE {parent} ATTACH PARTITION {legacy} "
            f"FOR VALUES FROM (MINVALUE) TO ('{hi!r}')"
        )
    )
    conn.execute(text(f"ALTER TABLE {legacy} DROP CONSTRAINT legacy_range"))


def upgrade() -> None:
    conn = op.get_bind()
    if conn.dialect.name != "postgresql":
        return
    # Whatever ran it (alembic's own command too): a big table's scan has no deadline.
    with db_deadline(None):
        conn.execute(text("SET LOCAL statement_timeout = 0"))
        _upgrade(conn)


def _upgrade(conn: Connection) -> None:
    schema = partition_schema(conn)
    conn.execute(text(f"CREATE SCHEMA IF NOT EXISTS {_q(schema)}"))
    for table, column, span in TABLES:
        legacy, pk = _to_legacy(conn, table, schema)
        create_partitioned(conn, table, column, like=legacy, primary_key=pk)
        _attach_legacy(conn, _q(table), legacy, column, span)
    _rollups(conn, schema)


def _rollups(conn: Connection, schema: str) -> None:
    legacy, pk = _to_legacy(conn, "rollups", schema)
    conn.execute(
        text(
            f"CREATE TABLE rollups (LIKE {legacy} INCLUDING DEFAULTS INCLUDING CONSTRAINTS) "
            "PARTITION BY LIST (bucket_s)"
        )
    )
    cols = ", ".join(_q(c) for c in pk)
    conn.execute(text(f"ALTER TABLE rollups ADD CONSTRAINT pk_rollups PRIMARY KEY ({cols})"))
    # Widths without partitions of their own (none today).
    create_default(conn, Series("rollups", "bucket_ts", _DAY))
    for width, span in ROLLUP_SPANS.items():
        series = Series(f"rollups_{width}", "bucket_ts", span, nested=True)
        conn.execute(
            text(
                f"CREATE TABLE {_q(schema)}.{_q(series.table)} PARTITION OF rollups "
                f"FOR VALUES IN ({width}) PARTITION BY RANGE (bucket_ts)"
            )
        )
        create_default(conn, series)
        if width == IN_PLACE_WIDTH:
            continue
        spans = conn.execute(
            text(
                f"SELECT DISTINCT floor((bucket_ts - {ORIGIN_S}) / {span}) FROM {legacy} "
                "WHERE bucket_s = :w"
            ),
            {"w": width},
        ).scalars()
        for n in sorted(spans):
            lo = ORIGIN_S + float(n) * span
            make_partition(conn, series, lo, lo + span, wait_ms=None)
    others = f"bucket_s <> {IN_PLACE_WIDTH}"
    conn.execute(text(f"INSERT INTO rollups SELECT * FROM {legacy} WHERE {others}"))
    conn.execute(text(f"DELETE FROM {legacy} WHERE {others}"))
    _attach_legacy(
        conn,
        f"{_q(schema)}.{_q(f'rollups_{IN_PLACE_WIDTH}')}",
        legacy,
        "bucket_ts",
        ROLLUP_SPANS[IN_PLACE_WIDTH],
        where=f"bucket_s = {IN_PLACE_WIDTH}",
    )


def downgrade() -> None:
    conn = op.get_bind()
    if conn.dialect.name != "postgresql":
        return
    with db_deadline(None):
        conn.execute(text("SET LOCAL statement_timeout = 0"))
        _downgrade(conn)


def _downgrade(conn: Connection) -> None:
    schema = partition_schema(conn)
    for table in [t for t, _, _ in TABLES] + ["rollups"]:
        pk = sa.inspect(conn).get_pk_constraint(table)["constrained_columns"]
        plain = f"{table}_plain"
        conn.execute(text(f"CREATE TABLE {_q(plain)} (LIKE {_q(table)} INCLUDING DEFAULTS)"))
        conn.execute(text(f"INSERT INTO {_q(plain)} SELECT * FROM {_q(table)}"))
        conn.execute(text(f"DROP TABLE {_q(table)}"))
        conn.execute(text(f"ALTER TABLE {_q(plain)} RENAME TO {_q(table)}"))
        cols = ", ".join(_q(c) for c in pk)
        conn.execute(
            text(f"ALTER TABLE {_q(table)} ADD CONSTRAINT {_q('pk_' + table)} PRIMARY KEY ({cols})")
        )
    left = conn.execute(
        text(
            "SELECT count(*) FROM pg_class c JOIN pg_namespace n ON n.oid = c.relnamespace "
            "WHERE n.nspname = :s"
        ),
        {"s": schema},
    ).scalar_one()
    if not left:
        conn.execute(text(f"DROP SCHEMA IF EXISTS {_q(schema)}"))
