"""Migration 0019_rollup_rows on a populated database, on SQLite and PostgreSQL: every rollup
row of the layout before (a row per metric) is in the new one (a row per bucket) and reads the
same, the downgrade gives back the same rows, and on PostgreSQL the new table is partitioned
as before (list by width, range by time) so that the keeper and the retention go on."""

from __future__ import annotations

import random
import time
from typing import Any

import pytest
from alembic import command
from sqlalchemy import Engine, MetaData, Table, text

from eqgw.store import partitions as parts
from eqgw.store import queries
from eqgw.store.engine import create_engine
from eqgw.store.errors import MigrationError
from eqgw.store.migrate import alembic_config, upgrade_engine
from eqgw.store.models import ROLLUP_METRICS, rollup_columns
from eqgw.store.retention import DAY_S, prune
from eqgw.store.writes import BUCKETS_S, Batch, load_unit_ids, write_batch

REVISION = "0019_rollup_rows"
BEFORE = "0018_partitions"
D0 = 1_780_000_000.0 - 1_780_000_000.0 % 86400  # a midnight
UNIT = ("V1/can0", 30)

Narrow = tuple[int, str, int, float, int, float, float, float]


def _populate(engine: Engine, now: float) -> list[Narrow]:
    """Rows of the layout before: three units, every width (and one no partition is made
    for), buckets holding every metric or a few, values that are not round in binary."""
    rnd = random.Random(7)
    rows: list[Narrow] = []
    with engine.begin() as conn:
        conn.execute(text("INSERT INTO vehicles (id, name) VALUES ('M', 'M')"))
        for i in (1, 2, 3):
            conn.execute(
                text("INSERT INTO units (bus, sa, vehicle_id) VALUES (:b, 30, 'M')"),
                {"b": f"M/can{i}"},
            )
        uids = [int(u) for u in conn.execute(text("SELECT id FROM units")).scalars()]
    for uid in uids:
        for width in (*BUCKETS_S, 300):
            first = now - 40 * DAY_S if width == 60 else now - 1300 * DAY_S
            first -= first % width
            for k in range(40):
                metrics = ROLLUP_METRICS if k % 3 else rnd.sample(ROLLUP_METRICS, 3)
                for m in metrics:
                    lo, hi = rnd.uniform(-50, 50), rnd.uniform(50, 150)
                    n = rnd.randint(1, 100_000)
                    ts = first + k * (width if width == 60 else 30 * DAY_S - width)
                    rows.append((uid, m, width, ts - ts % width, n, n * 0.1 * lo, lo, hi))
    with engine.begin() as conn:
        table = Table("rollups", MetaData(), autoload_with=conn)
        keys = ("unit_id", "metric", "bucket_s", "bucket_ts", "count", "sum", "min", "max")
        uniq = {r[:4]: r for r in rows}
        conn.execute(table.insert(), [dict(zip(keys, r, strict=True)) for r in uniq.values()])
    return sorted(uniq.values())


def _narrow(engine: Engine) -> list[Narrow]:
    with engine.connect() as conn:
        return [
            (r[0], r[1], r[2], r[3], r[4], r[5], r[6], r[7])
            for r in conn.execute(
                text(
                    "SELECT unit_id, metric, bucket_s, bucket_ts, count, sum, min, max "
                    "FROM rollups ORDER BY 1, 2, 3, 4"
                )
            )
        ]


def _wide(engine: Engine) -> list[Narrow]:
    """The rows of the new layout, a row per metric again."""
    out: list[Narrow] = []
    with engine.connect() as conn:
        for row in conn.execute(text("SELECT * FROM rollups")).mappings():
            for m in ROLLUP_METRICS:
                n, total, lo, hi = (row[c] for c in rollup_columns(m))
                if n is not None:
                    key = (row["unit_id"], m, row["bucket_s"], row["bucket_ts"])
                    out.append((*key, n, total, lo, hi))
    return sorted(out)


def _reads(engine: Engine, rows: list[Narrow]) -> dict[Any, Any]:
    """What the history reads of every unit and width give."""
    out = {}
    with engine.connect() as conn:
        for uid in sorted({r[0] for r in rows}):
            for width in (*BUCKETS_S, 300):
                got = queries.read_rollups(conn, uid, list(ROLLUP_METRICS), width, 0.0, 3e9)
                fp = queries.rollup_fingerprints(conn, uid, list(ROLLUP_METRICS), width, 0.0, 3e9)
                out[(uid, width)] = (got, fp)
    # The same from the rows themselves.
    for (uid, width), (got, fp) in out.items():
        for m in ROLLUP_METRICS:
            mine = [r for r in rows if r[0] == uid and r[1] == m and r[2] == width]
            assert [(p["ts"], p["count"], p["min"], p["max"]) for p in got[m]] == [
                (r[3], r[4], r[6], r[7]) for r in mine
            ]
            assert [p["avg"] for p in got[m]] == [r[5] / r[4] for r in mine]
            want = (
                (len(mine), sum(r[4] for r in mine), mine[0][3], mine[-1][3])
                if mine
                else (0, 0, None, None)
            )
            assert fp[m] == want
    return out


@pytest.mark.parametrize("engine_name", ["sqlite", "postgresql"])
def test_migration_moves_every_rollup_and_the_downgrade_gives_them_back(
    engine_name: str, request: pytest.FixtureRequest
) -> None:
    url: str = request.getfixturevalue("pg_url" if engine_name == "postgresql" else "sqlite_url")
    engine = create_engine(url)
    now = time.time()
    try:
        upgrade_engine(engine, BEFORE)
        if engine_name == "postgresql":  # the partitions the keeper made, as on a gateway
            parts.maintain(engine, raw_days=30, rollup_days=dict.fromkeys(BUCKETS_S, 3650))
        before = _populate(engine, now)
        assert _narrow(engine) == before
        n_buckets = len({r[:1] + r[2:4] for r in before})

        upgrade_engine(engine, REVISION)
        assert _wide(engine) == before
        with engine.connect() as conn:
            assert conn.execute(text("SELECT count(*) FROM rollups")).scalar_one() == n_buckets
        reads = _reads(engine, before)
        if engine_name == "postgresql":
            with engine.connect() as conn:
                assert parts.is_partitioned(conn, "rollups")
                for width in BUCKETS_S:
                    series = parts.rollup_series(width)
                    assert parts.is_partitioned(conn, series)
                    assert [p for p in parts.partitions(conn, series) if not p.default]
                schema = conn.execute(text("SELECT current_schema()")).scalar_one()
                aside = conn.execute(
                    text("SELECT to_regnamespace(:s)"), {"s": f"{schema}_rollups_old"}
                ).scalar_one()
                assert aside is None

        # The keeper, the writer and the retention on the migrated table.
        parts.maintain(engine, raw_days=30, rollup_days=dict.fromkeys(BUCKETS_S, 3650))
        b = Batch()
        b.vehicles["V1"] = {"id": "V1", "name": "Vehicle 1", "depot": "D"}
        b.units[UNIT] = "V1"
        minute = (now - 100) // 60 * 60  # ten samples in one minute: one bucket of every width
        b.measurements = [
            (UNIT, {"ts": minute + i, "v12": 12.0, "v24": 24.0, "i12": 0.0, "i24": 0.0})
            for i in range(10)
        ]
        with engine.begin() as conn:
            write_batch(conn, b, load_unit_ids(conn))
        after_write = _wide(engine)
        assert len(after_write) == len(before) + 4 * len(BUCKETS_S)  # v12..i24, each width
        command.downgrade(alembic_config(url), BEFORE)
        assert _narrow(engine) == after_write
        if engine_name == "postgresql":
            with engine.connect() as conn:
                assert parts.is_partitioned(conn, "rollups")
                assert parts.is_partitioned(conn, parts.rollup_series(60))
        upgrade_engine(engine, REVISION)  # and up again
        assert _wide(engine) == after_write

        # Retention by width: 1 minute buckets older than 30 days go, the others stay.
        result = prune(
            engine, raw_days=30, rollup_days=3650,
            rollup_days_by_width={60: 30, 900: 3650, 3600: 3650, 86400: 3650}, now=now,
        )  # fmt: skip
        assert result.deleted["rollups"] > 0
        left = _wide(engine)
        assert not [r for r in left if r[2] == 60 and r[3] < now - 31 * DAY_S]
        assert [r for r in left if r[2] == 900] == [r for r in after_write if r[2] == 900]
        assert reads  # read the same as the rows before (checked in _reads)
    finally:
        engine.dispose()


def test_a_metric_without_a_column_stops_the_upgrade_with_nothing_changed(
    sqlite_url: str,
) -> None:
    engine = create_engine(sqlite_url)
    try:
        upgrade_engine(engine, BEFORE)
        with engine.begin() as conn:
            conn.execute(
                text(
                    "INSERT INTO rollups (unit_id, metric, bucket_s, bucket_ts, count, sum, "
                    "min, max) VALUES (1, 'humidity', 60, 0, 1, 1, 1, 1)"
                )
            )
        rows = _narrow(engine)
        with pytest.raises(MigrationError, match="humidity"):
            upgrade_engine(engine, REVISION)
        assert _narrow(engine) == rows
    finally:
        engine.dispose()
