"""Time partitions on PostgreSQL (eqgw.store.partitions), the retention dropping them, rollup
retention per width on both engines, and migration 0018 up and down."""

from __future__ import annotations

import asyncio
import threading
import time
from collections.abc import Iterator
from typing import Any

import pytest
from alembic import command
from alembic.script import ScriptDirectory
from sqlalchemy import Engine, LargeBinary, MetaData, String, Table, inspect, text
from sqlalchemy.types import JSON, BigInteger, Double, Integer, SmallInteger

from eqgw.config import RetentionSettings
from eqgw.store import packed, queries
from eqgw.store import partitions as parts
from eqgw.store.engine import create_engine
from eqgw.store.migrate import alembic_config, upgrade_engine
from eqgw.store.models import RAW_TABLES, all_metadata
from eqgw.store.partition_keeper import TASK_NAME, PartitionKeeper
from eqgw.store.retention import DAY_S, prune
from eqgw.store.writes import BUCKETS_S, Batch, load_unit_ids, write_batch
from eqgw.supervisor import Supervisor

UNIT = ("V1/can0", 30)
D0 = 1_780_000_000.0 - 1_780_000_000.0 % 86400  # a midnight (2026-05-29)
WIDTHS = {60: 30.0, 900: 365.0, 3600: 1826.0, 86400: 1826.0}


@pytest.fixture
def pg(pg_url: str) -> Iterator[Engine]:
    """A PostgreSQL schema at the latest revision."""
    eng = create_engine(pg_url)
    upgrade_engine(eng)
    try:
        yield eng
    finally:
        eng.dispose()


def _write(engine: Engine, times: list[float]) -> None:
    b = Batch()
    b.vehicles["V1"] = {"id": "V1", "name": "Vehicle 1", "depot": "D"}
    b.units[UNIT] = "V1"
    b.measurements = [
        (UNIT, {"ts": t, "v12": 12.0, "v24": 24.0, "i12": 0.0, "i24": 0.0}) for t in times
    ]
    with engine.begin() as conn:
        write_batch(conn, b, load_unit_ids(conn))


def _times(engine: Engine, table: str = "measurements", col: str = "ts") -> list[float]:
    with engine.connect() as conn:
        return [
            float(t)
            for t in conn.execute(text(f"SELECT {col} FROM {table} ORDER BY {col}")).scalars()
        ]


def _buckets(engine: Engine) -> dict[int, list[float]]:
    out: dict[int, list[float]] = {w: [] for w in BUCKETS_S}
    with engine.connect() as conn:
        for w, t in conn.execute(
            text(
                "SELECT bucket_s, bucket_ts FROM rollups WHERE v12_n IS NOT NULL ORDER BY bucket_ts"
            )
        ):
            out[int(w)].append(float(t))
    return out


def _default_rows(engine: Engine, table: str) -> int:
    with engine.connect() as conn:
        schema = parts.partition_schema(conn)
        return int(
            conn.execute(text(f'SELECT count(*) FROM "{schema}"."{table}_default"')).scalar_one()
        )


def _ranges(engine: Engine, series: parts.Series) -> list[tuple[float | None, float | None]]:
    with engine.connect() as conn:
        return [(p.lo, p.hi) for p in parts.partitions(conn, series) if not p.default]


def _maintain(
    engine: Engine,
    now: float,
    ahead_days: float = 3.0,
    keep_days: float = 30.0,
    lock_wait_s: float = parts.LOCK_WAIT_S,
) -> parts.MaintainResult:
    return parts.maintain(
        engine,
        raw_days=keep_days,
        rollup_days=dict.fromkeys(BUCKETS_S, keep_days),
        ahead_days=ahead_days,
        now=now,
        lock_wait_s=lock_wait_s,
    )


# -- partitions made ahead, no row lost ------------------------------------------------------


def test_every_time_series_table_is_partitioned_with_a_default(pg: Engine) -> None:
    with pg.connect() as conn:
        for series in parts.all_series():
            assert parts.is_partitioned(conn, series), series
            assert any(p.default for p in parts.partitions(conn, series)), series
        assert parts.is_partitioned(conn, "rollups")
        # The application's schema shows the tables, not their partitions.
        names = set(inspect(conn).get_table_names())
    assert {t.name for t in RAW_TABLES} | {"rollups"} <= names
    assert not any(n.endswith("_default") or "_p2" in n for n in names)


def test_partitions_are_made_ahead_once(pg: Engine) -> None:
    now = D0 + 3600
    made = _maintain(pg, now, ahead_days=3)
    day = parts.TIME_TABLES["measurements"]
    # From yesterday's day to the one 3 days ahead.
    assert _ranges(pg, day) == [(D0 + k * DAY_S, D0 + (k + 1) * DAY_S) for k in range(-1, 4)]
    week = parts.TIME_TABLES["messages"]
    (lo, hi), *_ = _ranges(pg, week)
    assert lo is not None and hi == lo + 7 * DAY_S and lo <= now - DAY_S < hi
    assert time.gmtime(lo).tm_wday == 0  # weeks start on Monday
    assert made.made and not made.skipped
    assert _maintain(pg, now, ahead_days=3).made == []  # nothing new the second time


def test_rows_outside_every_partition_land_in_the_default_and_move_out_later(pg: Engine) -> None:
    now = D0 + 3600
    _maintain(pg, now)
    replayed_2019 = [1_560_000_000.0 + i for i in range(5)]  # past any retention
    last_week = [now - 8 * DAY_S + i for i in range(5)]  # inside the retention, no partition
    jumped = [now + 40 * DAY_S + i for i in range(5)]  # a clock that jumped ahead
    _write(pg, replayed_2019 + last_week + jumped)
    everything = sorted(replayed_2019 + last_week + jumped)
    assert _times(pg) == everything
    assert _default_rows(pg, "measurements") == 15
    result = _maintain(pg, now)
    assert result.moved >= 10
    assert _times(pg) == everything  # nothing lost, nothing doubled
    assert _default_rows(pg, "measurements") == 5  # the 2019 rows: the retention's to delete
    lo = parts.span_start(last_week[0], DAY_S)
    assert (lo, lo + DAY_S) in _ranges(pg, parts.TIME_TABLES["measurements"])
    # Rows the default holds for a range made ahead later move into it.
    tomorrow_plus = [now + 5 * DAY_S + i for i in range(3)]
    _write(pg, tomorrow_plus)
    _maintain(pg, now + 3 * DAY_S)
    assert _times(pg) == sorted(everything + tomorrow_plus)
    assert _default_rows(pg, "measurements") == 5
    # The retention deletes the default's old rows exactly.
    prune(pg, raw_days=30, rollup_days=3650, rollup_days_by_width=WIDTHS, now=now)
    assert _default_rows(pg, "measurements") == 0
    assert _times(pg) == sorted(last_week + jumped + tomorrow_plus)


# -- the retention drops whole partitions ----------------------------------------------------


@pytest.mark.parametrize("cut_at", [5.5, 5.0], ids=["mid-partition", "on-a-boundary"])
def test_prune_drops_old_partitions_and_keeps_every_newer_row(pg: Engine, cut_at: float) -> None:
    times = [D0 + k * 3600.0 for k in range(10 * 24)]  # hourly, ten days
    _maintain(pg, D0 + DAY_S, ahead_days=10)
    _write(pg, times)
    assert _default_rows(pg, "measurements") == 0
    cutoff = D0 + cut_at * DAY_S
    result = prune(
        pg, raw_days=1, rollup_days=3650, rollup_days_by_width=WIDTHS, now=cutoff + DAY_S
    )
    left = _times(pg)
    # Every row at or after the cutoff stays; a partition goes only once its whole day is
    # older than the cutoff: the rows of the cutoff's own day stay with it (day granularity).
    assert [t for t in times if t >= cutoff] == [t for t in left if t >= cutoff]
    assert left == [t for t in times if t >= D0 + 5 * DAY_S]
    assert len(result.dropped["measurements"]) == 5
    assert result.deleted["measurements"] == 5 * 24
    # Rollups were untouched (their retention is years).
    assert _buckets(pg)[86400] == [D0 + k * DAY_S for k in range(10)]


def test_retention_deletes_exactly_on_sqlite(sqlite_url: str) -> None:
    engine = create_engine(sqlite_url)
    upgrade_engine(engine)
    times = [D0 + k * 3600.0 for k in range(10 * 24)]
    _write(engine, times)
    cutoff = D0 + 5.5 * DAY_S
    result = prune(
        engine, raw_days=1, rollup_days=3650, rollup_days_by_width=WIDTHS, now=cutoff + DAY_S
    )
    assert _times(engine) == [t for t in times if t >= cutoff]
    assert result.dropped == {}
    engine.dispose()


def test_rollup_retention_per_width(engine: Engine) -> None:
    now = D0 + 40 * DAY_S
    times = [D0 + k * 6 * 3600.0 + 30 for k in range(40 * 4)]  # every 6 h for 40 days
    _write(engine, times)
    if engine.dialect.name == "postgresql":
        _maintain(engine, now, keep_days=3650)  # every bucket into partitions of its own
        with engine.connect() as conn:
            schema = parts.partition_schema(conn)
            assert (
                conn.execute(
                    text(f'SELECT count(*) FROM "{schema}".rollups_60_default')
                ).scalar_one()
                == 0
            )
    before = _buckets(engine)
    days = {60: 10.0, 900: 20.0, 3600: 30.0, 86400: 1000.0}
    result = prune(engine, raw_days=3650, rollup_days=3650, rollup_days_by_width=days, now=now)
    after = _buckets(engine)
    spans = parts.ROLLUP_SPANS
    for width, keep in days.items():
        cutoff = now - keep * DAY_S
        assert [t for t in after[width] if t >= cutoff] == [t for t in before[width] if t >= cutoff]
        if engine.dialect.name == "postgresql":
            # Whole partitions: nothing older than the cutoff's partition is left.
            assert all(t >= parts.span_start(cutoff, spans[width]) for t in after[width]), width
        else:
            assert all(t >= cutoff for t in after[width]), width
    assert after[60] and after[60][0] >= now - 11 * DAY_S
    assert after[86400] == before[86400]  # 1000 days: nothing of the 40 goes
    assert result.deleted["rollups"] > 0
    # Raw rows have their own retention (ten years here): all stay.
    assert _times(engine) == times


def test_retention_settings_default_per_width() -> None:
    r = RetentionSettings()
    assert r.rollup_days_by_width() == {60: 30, 900: 365, 3600: 1826, 86400: 1826}
    assert set(r.rollup_days_by_width()) == set(BUCKETS_S) == set(parts.ROLLUP_SPANS)


# -- several gateways ------------------------------------------------------------------------


def test_two_gateways_racing_make_each_partition_once(pg_url: str, pg: Engine) -> None:
    engines = [create_engine(pg_url) for _ in range(2)]
    now = D0 + 3600
    barrier = threading.Barrier(2)
    results: list[parts.MaintainResult] = []
    errors: list[BaseException] = []

    def run(eng: Engine) -> None:
        try:
            for i in range(5):
                barrier.wait(timeout=30)
                results.append(_maintain(eng, now + i * DAY_S))
        except BaseException as exc:  # reported below
            errors.append(exc)

    threads = [threading.Thread(target=run, args=(e,)) for e in engines]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=120)
    for e in engines:
        e.dispose()
    assert not errors, errors
    made = [n for r in results for n in r.made]
    assert len(made) == len(set(made))  # no partition made twice
    got = _ranges(pg, parts.TIME_TABLES["measurements"])
    assert got == [(D0 + k * DAY_S, D0 + (k + 1) * DAY_S) for k in range(-1, 8)]


def test_a_held_lock_skips_the_round_and_the_partition_drops(pg: Engine) -> None:
    _maintain(pg, D0 + DAY_S, ahead_days=5)
    _write(pg, [D0 + k * 3600.0 for k in range(5 * 24)])
    with pg.connect() as other, parts.partition_lock(other) as held:
        assert held
        assert _maintain(pg, D0 + 3 * DAY_S, lock_wait_s=0).skipped
        # Waiting for it ends in time too.
        assert _maintain(pg, D0 + 3 * DAY_S, lock_wait_s=0.5).skipped
        result = prune(
            pg, raw_days=1, rollup_days=3650, rollup_days_by_width=WIDTHS, now=D0 + 4 * DAY_S,
            lock_wait_s=0,
        )  # fmt: skip
        assert result.dropped == {} and len(_times(pg)) == 5 * 24
    result = prune(
        pg, raw_days=1, rollup_days=3650, rollup_days_by_width=WIDTHS, now=D0 + 4 * DAY_S
    )
    assert len(result.dropped["measurements"]) == 3


def _stats(engine: Engine, name: str) -> tuple[int, int, int]:
    """(bytes, live tuples, dead tuples) of a partition, once the statistics show its last
    changes (they are flushed as sessions end)."""
    engine.dispose()
    with engine.connect() as conn:
        schema = parts.partition_schema(conn)
        row = conn.execute(
            text(
                "SELECT pg_total_relation_size(c.oid), coalesce(s.n_live_tup, 0), "
                "coalesce(s.n_dead_tup, 0) FROM pg_class c LEFT JOIN pg_stat_user_tables s "
                "ON s.relid = c.oid WHERE c.oid = to_regclass(:t)"
            ),
            {"t": f'"{schema}"."{name}"'},
        ).one()
    return int(row[0]), int(row[1]), int(row[2])


def _settled(engine: Engine, name: str, ok: Any) -> tuple[int, int, int]:
    deadline = time.monotonic() + 15.0
    while True:
        got = _stats(engine, name)
        if ok(got) or time.monotonic() > deadline:
            return got
        time.sleep(0.2)


def test_a_past_partition_packed_whole_is_truncated_not_left_dead(pg: Engine) -> None:
    now = time.time()
    day = parts.span_start(now - 3 * DAY_S, DAY_S)
    _maintain(pg, day)
    _write(pg, [day + 7.0 * i for i in range(3000)])  # about six hours
    with pg.begin() as conn:
        conn.execute(text("UPDATE units SET last_seen = :t"), {"t": now})
        uid = load_unit_ids(conn)[UNIT]
    with pg.connect() as conn:
        want = queries.series(conn, uid, "v12", day, day + DAY_S)
        (part,) = [
            p.name for p in parts.partitions(conn, parts.TIME_TABLES["measurements"]) if p.lo == day
        ]
    assert len(want) == 3000
    assert packed.compact(pg, now=now) == 3000
    size, live, dead = _settled(pg, part, lambda s: s[2] >= 3000)
    assert (live, dead) == (0, 3000) and size > 0  # what VACUUM would have to clean
    result = _maintain(pg, now)
    assert part in result.truncated
    size, live, dead = _settled(pg, part, lambda s: s[1:] == (0, 0))
    assert (live, dead) == (0, 0) and size <= 8192  # the index's metapage
    with pg.connect() as conn:
        assert queries.series(conn, uid, "v12", day, day + DAY_S) == want  # from the blocks
    # A partition holding a row (one not packed yet) is left alone.
    with pg.begin() as conn:
        conn.execute(
            text("INSERT INTO measurements (unit_id, ts, v12) VALUES (:u, :t, 1)"),
            {"u": uid, "t": day + 12 * 3600.5},
        )
        conn.execute(
            text("DELETE FROM measurements WHERE unit_id = :u AND ts = :t"),
            {"u": uid, "t": day + 12 * 3600.5},
        )
        conn.execute(
            text("INSERT INTO measurements (unit_id, ts, v12) VALUES (:u, :t, 2)"),
            {"u": uid, "t": day + 13 * 3600.5},
        )
    _settled(pg, part, lambda s: s[1] == 1)
    assert part not in _maintain(pg, now).truncated
    with pg.connect() as conn:
        assert len(queries.series(conn, uid, "v12", day, day + DAY_S)) == 3001


def test_the_keeper_runs_supervised_on_postgres_only(pg: Engine, sqlite_url: str) -> None:
    async def main() -> None:
        tasks = Supervisor()
        async with PartitionKeeper(pg, RetentionSettings(), tasks) as keeper:
            # Made before the block starts (before the ingest writes): a partition made for
            # now while rows are routed to the default fails their writes.
            assert keeper.last is not None and keeper.last.made
            today = parts.span_start(time.time(), DAY_S)
            assert (today, today + DAY_S) in _ranges(pg, parts.TIME_TABLES["measurements"])
            status = tasks.get(TASK_NAME)
            assert status is not None and status.state == "running"
        assert keeper.last.made  # today's partitions and those ahead
        lite = create_engine(sqlite_url)
        async with PartitionKeeper(lite, RetentionSettings(), tasks):
            pass
        lite.dispose()
        await tasks.stop()

    asyncio.run(main())
    today = parts.span_start(time.time(), DAY_S)
    assert (today, today + DAY_S) in _ranges(pg, parts.TIME_TABLES["measurements"])


# -- migration 0018 ----------------------------------------------------------------------------

REVISION = "0018_partitions"
BEFORE = str(ScriptDirectory.from_config(alembic_config()).get_revision(REVISION).down_revision)
_TABLES = [t.name for t in RAW_TABLES] + ["rollups"]


def _value(col: Any, i: int) -> Any:
    t = col.type
    if col.name == "unit_id":
        return 1 + i % 2
    if isinstance(t, LargeBinary):
        return bytes([i % 256]) * 3
    if isinstance(t, JSON):
        return {"i": i}
    if isinstance(t, String):
        return f"n{i % 3}"
    if isinstance(t, Double):
        return float(i) / 4
    if isinstance(t, SmallInteger | Integer | BigInteger):
        return i % 5
    raise AssertionError(col)


def _populate(engine: Engine, per_table: int) -> None:
    metadata = all_metadata()
    with engine.begin() as conn:
        for name in _TABLES:
            table: Table = metadata.tables[name]
            if name == "rollups":  # as this revision has it (a row per metric), not the model
                table = Table(name, MetaData(), autoload_with=conn)
            rows = []
            for i in range(per_table):
                row = {c.name: _value(c, i) for c in table.columns}
                if name == "rollups":
                    row["bucket_s"] = (60, 900, 3600, 86400, 300)[i % 5]
                    row["bucket_ts"] = D0 - 3 * DAY_S + i * 900.0
                else:
                    row["ts"] = D0 - 3 * DAY_S + i * 977.0  # spread over a few days and weeks
                rows.append(row)
            conn.execute(table.insert(), rows)


def _snapshot(engine: Engine) -> dict[str, list[tuple[Any, ...]]]:
    out = {}
    with engine.connect() as conn:
        for name in _TABLES:
            pk = inspect(conn).get_pk_constraint(name)["constrained_columns"]
            order = ", ".join(pk)
            out[name] = [
                tuple(r) for r in conn.execute(text(f"SELECT * FROM {name} ORDER BY {order}"))
            ]
    return out


def test_migration_partitions_a_populated_database_and_back(pg_url: str) -> None:
    engine = create_engine(pg_url)
    upgrade_engine(engine, BEFORE)
    _populate(engine, 400)
    ahead = time.time() + 10 * DAY_S  # a row of a clock that was ahead
    with engine.begin() as conn:
        conn.execute(text("INSERT INTO measurements (unit_id, ts) VALUES (1, :t)"), {"t": ahead})
    before = _snapshot(engine)
    assert all(len(rows) == 400 for name, rows in before.items() if name != "measurements")
    upgrade_engine(engine, REVISION)
    assert _snapshot(engine) == before
    with engine.connect() as conn:
        for name in _TABLES:
            assert parts.is_partitioned(conn, name)
        # The old table is one partition up to the end of its newest row's span; 1-minute
        # rollups stayed in it, the other widths were copied into partitions of their own.
        (legacy,) = [
            p for p in parts.partitions(conn, "measurements") if p.name.endswith("_legacy")
        ]
        assert legacy.lo == float("-inf") and legacy.hi is not None
        # ... not into the future: the row stamped ahead went to the default partition.
        assert legacy.hi <= parts.span_start(time.time(), DAY_S) + DAY_S
        assert any(
            p.name.endswith("_legacy") for p in parts.partitions(conn, parts.rollup_series(60))
        )
        assert [p.name for p in parts.partitions(conn, parts.rollup_series(900)) if not p.default]
    # New rows go on being written, after the old table's range too.
    _maintain(engine, time.time())
    now = time.time()
    with engine.begin() as conn:  # as the writer of this revision wrote them
        conn.execute(
            text("INSERT INTO measurements (unit_id, ts, v12) VALUES (1, :t, 12)"), {"t": now}
        )
        conn.execute(
            text(
                "INSERT INTO rollups (unit_id, metric, bucket_s, bucket_ts, count, sum, min, max) "
                "VALUES (1, 'v12', 60, :b, 1, 12, 12, 12)"
            ),
            {"b": now // 60 * 60},
        )
    after_write = _snapshot(engine)
    assert len(after_write["measurements"]) == 402
    command.downgrade(alembic_config(pg_url), BEFORE)
    assert _snapshot(engine) == after_write
    with engine.connect() as conn:
        for name in _TABLES:
            assert not parts.is_partitioned(conn, name)
            assert inspect(conn).get_pk_constraint(name)["name"] == f"pk_{name}"
        schema = parts.partition_schema(conn)
        assert conn.execute(text("SELECT to_regnamespace(:s)"), {"s": schema}).scalar_one() is None
    upgrade_engine(engine, REVISION)  # and up again
    assert _snapshot(engine) == after_write
    engine.dispose()


def test_migration_leaves_sqlite_unchanged(sqlite_url: str) -> None:
    engine = create_engine(sqlite_url)
    upgrade_engine(engine, BEFORE)

    def schema() -> list[tuple[Any, ...]]:
        with engine.connect() as conn:
            return [
                tuple(r)
                for r in conn.execute(
                    text(
                        "SELECT type, name, sql FROM sqlite_master "
                        "WHERE name != 'alembic_version' ORDER BY name"
                    )
                )
            ]

    before = schema()
    upgrade_engine(engine, REVISION)
    assert schema() == before
    command.downgrade(alembic_config(sqlite_url), BEFORE)
    assert schema() == before
    engine.dispose()
