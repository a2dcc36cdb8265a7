"""Store queries, rollups, retention and migrations on SQLite and PostgreSQL."""

from __future__ import annotations

import math
import random
import threading
from typing import Any

import pytest
from alembic import command
from alembic.autogenerate import compare_metadata
from alembic.runtime.migration import MigrationContext
from sqlalchemy import Engine, Table, event, insert, inspect, select, text

from eqgw.store import queries
from eqgw.store.engine import create_engine, is_sqlite, sync_url
from eqgw.store.errors import DatabaseUrlError
from eqgw.store.migrate import alembic_config, current_revision, head_revision, upgrade_engine
from eqgw.store.models import all_metadata
from eqgw.store.retention import DAY_S, prune
from eqgw.store.webhook_models import Webhook, WebhookDelivery
from eqgw.store.writes import BUCKETS_S, Batch, load_unit_ids, write_batch

UNIT = ("V1/can0", 30)


def _write(engine: Engine, batch: Batch) -> None:
    with engine.begin() as conn:
        write_batch(conn, batch, load_unit_ids(conn))


def _batch(
    measurements: list[dict[str, Any]], battery: list[dict[str, Any]] | None = None
) -> Batch:
    b = Batch()
    b.vehicles["V1"] = {"id": "V1", "name": "Vehicle 1", "depot": "D"}
    b.units[UNIT] = "V1"
    b.measurements = [(UNIT, m) for m in measurements]
    cols = [c.name for c in all_metadata().tables["battery_states"].columns][1:]
    b.battery_states = [(UNIT, {c: r.get(c) for c in cols}) for r in battery or []]
    return b


def _random_measurements(seed: int, n: int, start: float) -> list[dict[str, Any]]:
    rng = random.Random(seed)
    ts = start
    out = []
    for _ in range(n):
        ts += rng.choice([0.5, 3.0, 3.0, 3.0, 47.0, 400.0])
        out.append(
            {
                "ts": round(ts, 3),
                "v12": round(rng.uniform(11, 15), 3),
                "v24": round(rng.uniform(22, 29), 3),
                "i12": None if rng.random() < 0.1 else round(rng.uniform(-50, 50), 2),
                "i24": round(rng.uniform(-80, 80), 2),
            }
        )
    return out


def test_migrations_match_models_and_downgrade(engine: Engine, db_url: str) -> None:
    assert current_revision(engine) == head_revision()
    with engine.connect() as conn:
        diff = compare_metadata(MigrationContext.configure(conn), all_metadata())
    assert diff == []
    names = set(inspect(engine).get_table_names())
    metadata = all_metadata()
    assert set(metadata.tables) <= names
    pk = inspect(engine).get_pk_constraint("measurements")
    assert pk["name"] == "pk_measurements"
    cfg = alembic_config(db_url)
    command.downgrade(cfg, "base")
    assert not set(metadata.tables) & set(inspect(engine).get_table_names())
    upgrade_engine(engine)
    assert current_revision(engine) == head_revision()
    if is_sqlite(db_url):
        with engine.connect() as conn:
            assert conn.exec_driver_sql("PRAGMA journal_mode").scalar() == "wal"
            assert conn.exec_driver_sql("PRAGMA busy_timeout").scalar() > 0


def test_raw_frame_sequence_migrates_existing_rows(empty_db_url: str) -> None:
    """The raw archive's key gains the frame's place among frames stamped alike: archived
    rows stay (at place 0), the table stays clustered on its key on SQLite, and two frames
    of one id and timestamp can then both be kept."""
    engine = create_engine(empty_db_url)
    try:
        upgrade_engine(engine, "0006")
        with engine.begin() as conn:
            conn.execute(text("INSERT INTO vehicles (id, name) VALUES ('V1', 'V1')"))
            conn.execute(
                text("INSERT INTO units (bus, sa, vehicle_id) VALUES ('V1/can0', 30, 'V1')")
            )
            uid = conn.execute(text("SELECT id FROM units")).scalar_one()
            for ts, data in ((1.0, b"\x01"), (2.0, b"\x02")):
                conn.execute(
                    text("INSERT INTO raw_frames VALUES (:u, :ts, 419364382, :d)"),
                    {"u": uid, "ts": ts, "d": data},
                )
        # Up to the revision under test (0012 moves raw_frames into raw_blocks).
        upgrade_engine(engine, "0007")
        with engine.begin() as conn:
            rows = conn.execute(
                text("SELECT ts, can_id, seq, data FROM raw_frames ORDER BY ts")
            ).all()
            assert [(r.ts, r.seq, bytes(r.data)) for r in rows] == [
                (1.0, 0, b"\x01"),
                (2.0, 0, b"\x02"),
            ]
            conn.execute(
                text("INSERT INTO raw_frames (unit_id, ts, can_id, seq, data) "
                     "VALUES (:u, 1.0, 419364382, 1, :d)"),
                {"u": uid, "d": b"\x03"},
            )  # fmt: skip
            assert conn.execute(text("SELECT count(*) FROM raw_frames")).scalar_one() == 3
            if is_sqlite(empty_db_url):
                ddl = conn.execute(
                    text("SELECT sql FROM sqlite_master WHERE name = 'raw_frames'")
                ).scalar_one()
                assert "WITHOUT ROWID" in ddl.upper()
        pk = inspect(engine).get_pk_constraint("raw_frames")
        assert pk["name"] == "pk_raw_frames"
        assert pk["constrained_columns"] == ["unit_id", "ts", "can_id", "seq"]
    finally:
        engine.dispose()


def test_url_mapping() -> None:
    assert sync_url("postgresql+asyncpg://u@h/db").drivername == "postgresql+psycopg"
    assert sync_url("postgres://u@h/db").drivername == "postgresql+psycopg"
    assert sync_url("sqlite+aiosqlite:///x.db").drivername == "sqlite"
    with pytest.raises(DatabaseUrlError):
        sync_url("mysql://u@h/db")
    with pytest.raises(DatabaseUrlError):
        sync_url("not a url")


def test_downsampled_series_equal_raw_aggregates(engine: Engine) -> None:
    rows = _random_measurements(1, 3000, 1_700_000_000.0)
    # Written in several batches, out of order, one batch twice: rollups must not care.
    chunks = [rows[i : i + 700] for i in range(0, len(rows), 700)]
    for chunk in reversed(chunks):
        _write(engine, _batch(chunk))
    _write(engine, _batch(chunks[1]))
    start, end = rows[0]["ts"] - 86400, rows[-1]["ts"] + 86400
    with engine.connect() as conn:
        uid = queries.unit_id_of(conn, *UNIT)
        assert uid is not None
        for metric in ("v12", "v24", "i12", "i24"):
            raw = queries.series(conn, uid, metric, start, end, "raw")
            assert [p["ts"] for p in raw] == [r["ts"] for r in rows if r[metric] is not None]
            for resolution, width in (("1m", 60), ("15m", 900), ("1h", 3600), ("1d", 86400)):
                got = queries.series(conn, uid, metric, start, end, resolution)
                sql = (
                    f"SELECT floor(ts / {width}) * {width} AS b, count({metric}), "
                    f"sum({metric}), min({metric}), max({metric}) FROM measurements "
                    f"WHERE unit_id = :u AND {metric} IS NOT NULL GROUP BY 1 ORDER BY 1"
                )
                want = conn.execute(text(sql), {"u": uid}).all()
                assert [g["ts"] for g in got] == [float(w[0]) for w in want]
                for g, (_, n, total, lo, hi) in zip(got, want, strict=True):
                    assert g["count"] == n
                    assert g["min"] == lo and g["max"] == hi
                    assert math.isclose(g["avg"], total / n, rel_tol=1e-9)
        # Several metrics in one call (the history endpoint's path) give the same series.
        names = ["i24", "v12", "i12"]
        for resolution in ("raw", "1m", "1h"):
            many = queries.series_many(conn, uid, names, start, end, resolution)
            assert list(many) == names
            for metric in names:
                assert many[metric] == queries.series(conn, uid, metric, start, end, resolution)
                assert many[metric]
        assert len(queries.series_many(conn, uid, ["v12"], start, end, "1m", limit=3)["v12"]) == 3
        with pytest.raises(queries.UnknownMetricError):
            queries.series_many(conn, uid, ["v12", "nope"], start, end, "1m")
    assert BUCKETS_S == (60, 900, 3600, 86400)


def _rollup(conn: Any, uid: int, metric: str, width: int) -> list[tuple[Any, ...]]:
    return [
        tuple(r)
        for r in conn.execute(
            text(
                f"SELECT bucket_ts, {metric}_n, {metric}_sum, {metric}_min, {metric}_max "
                f"FROM rollups WHERE unit_id = :u AND {metric}_n IS NOT NULL "
                "AND bucket_s = :w ORDER BY bucket_ts"
            ),
            {"u": uid, "w": width},
        )
    ]


def test_a_key_repeated_within_a_batch_is_stored_and_rolled_up_once(engine: Engine) -> None:
    t0 = 1_700_000_040.0
    rows = [{"ts": t0 + i, "v12": 12.0 + i, "v24": 25.0, "i12": None, "i24": 1.0} for i in range(5)]
    repeat = {**rows[2], "v12": 99.0}  # same key, other value: the first row of a key wins
    with engine.begin() as conn:
        result = write_batch(conn, _batch([*rows, repeat]), load_unit_ids(conn))
    assert result.inserted["measurements"] == 5
    with engine.connect() as conn:
        uid = queries.unit_id_of(conn, *UNIT)
        assert uid is not None
        assert [p["value"] for p in queries.series(conn, uid, "v12", 0, 2e9)] == [
            12.0,
            13.0,
            14.0,
            15.0,
            16.0,
        ]
        assert _rollup(conn, uid, "v12", 3600) == [(1_699_999_200.0, 5, 70.0, 12.0, 16.0)]
        assert _rollup(conn, uid, "i12", 60) == []  # all null: no bucket


@pytest.mark.postgres
def test_pg_writer_racing_another_on_the_same_keys_stores_each_row_once(pg_url: str) -> None:
    """Two writers commit overlapping rows at the same time. The second checks for stored
    keys before the first commits, so its COPY meets the first's rows (it waits for their
    commit, then fails on the unique key) and the batch falls back to INSERT ... ON CONFLICT
    within the same transaction: each row stored once, the rollups counting each once."""
    import threading

    eng = create_engine(pg_url)
    upgrade_engine(eng)
    try:
        _write(eng, _batch([]))  # the unit exists before the race
        t0 = 1_700_000_000.0
        rows = [
            {"ts": t0 + i, "v12": 12.0 + i / 100, "v24": 25.0, "i12": 1.0, "i24": 2.0}
            for i in range(300)
        ]
        first, second = rows[:200], rows[100:]  # 100 rows in both
        with eng.connect() as c1:
            ids = load_unit_ids(c1)
            r1 = write_batch(c1, _batch(first), ids)  # autobegun, not committed yet
            done: dict[str, Any] = {}

            def race() -> None:
                with eng.begin() as c2:
                    done["result"] = write_batch(c2, _batch(second), ids)

            t = threading.Thread(target=race)
            t.start()
            t.join(1.0)
            assert t.is_alive(), "the second writer should wait for the first one's keys"
            c1.commit()
            t.join(10)
            assert not t.is_alive()
        assert r1.inserted["measurements"] == 200
        assert done["result"].inserted["measurements"] == 100
        with eng.connect() as conn:
            uid = queries.unit_id_of(conn, *UNIT)
            assert uid is not None
            n = conn.execute(text("SELECT count(*) FROM measurements")).scalar_one()
            assert n == 300
            want = conn.execute(
                text(
                    "SELECT floor(ts / 60) * 60, count(v12), sum(v12), min(v12), max(v12) "
                    "FROM measurements GROUP BY 1 ORDER BY 1"
                )
            ).all()
            got = _rollup(conn, uid, "v12", 60)
            assert [g[:2] for g in got] == [(float(w[0]), w[1]) for w in want]
            for g, w in zip(got, want, strict=True):
                assert math.isclose(g[2], w[2], rel_tol=1e-12) and g[3:] == tuple(w[3:])
    finally:
        eng.dispose()


def test_battery_metrics_and_ranges(engine: Engine) -> None:
    t0 = 1_700_000_000.0
    battery = [
        {"ts": t0 + i, "idx": 2, "battery": "12v", "soc": 50.0 + i, "dod": 10.0} for i in range(10)
    ] + [{"ts": t0 + i, "idx": 5, "temperature_c": 20.0 + i} for i in range(10)]
    _write(engine, _batch([], battery))
    with engine.connect() as conn:
        uid = queries.unit_id_of(conn, *UNIT)
        assert uid is not None
        assert [p["value"] for p in queries.series(conn, uid, "soc_12v", t0, t0 + 5)] == [
            50.0,
            51.0,
            52.0,
            53.0,
            54.0,
        ]
        (bucket,) = queries.series(conn, uid, "temperature_c", 0, 2e9, "1d")
        assert (bucket["count"], bucket["min"], bucket["max"]) == (10, 20.0, 29.0)
        assert queries.series(conn, uid, "soc_24v", 0, 2e9, "1h") == []
        with pytest.raises(queries.UnknownMetricError):
            queries.series(conn, uid, "nope", 0, 1)
        with pytest.raises(queries.UnknownMetricError):
            queries.series(conn, uid, "v12", 0, 1, "5m")
    assert "soc_12v" in queries.metrics()
    assert queries.pick_resolution(0, 3000) == "raw"
    assert queries.pick_resolution(0, 86400 * 7) == "15m"


def test_episodes_live_state_and_units(engine: Engine) -> None:
    b = _batch([])
    b.episodes[(UNIT, "OVF", 100.0)] = {
        "fault": "OVF",
        "spn": 168,
        "fmi": 0,
        "source": "dm1",
        "state": "active",
        "started_at": 100.0,
        "last_seen_at": 100.0,
        "ended_at": None,
        "ended_by": None,
        "occurrence_count": 3,
    }
    b.live[(UNIT, "voltages")] = {"ts": 200.0, "fields": {"v12": 13.1}}
    b.seen[UNIT] = [100.0, 200.0]
    b.unit_info[UNIT] = {"model": "EQ8001", "series": 80}
    _write(engine, b)
    # The same episode closes later; an older live value does not overwrite a newer one.
    b2 = _batch([])
    b2.episodes[(UNIT, "OVF", 100.0)] = {
        **b.episodes[(UNIT, "OVF", 100.0)],
        "state": "closed",
        "ended_at": 150.0,
        "ended_by": "dm1_all_clear",
    }
    b2.live[(UNIT, "voltages")] = {"ts": 50.0, "fields": {"v12": 1.0}}
    b2.seen[UNIT] = [50.0, 60.0]
    _write(engine, b2)
    with engine.connect() as conn:
        uid = queries.unit_id_of(conn, *UNIT)
        assert uid is not None
        (ep,) = queries.fault_episodes(conn, uid)
        assert (ep["state"], ep["ended_at"], ep["occurrence_count"]) == ("closed", 150.0, 3)
        assert queries.fault_episodes(conn, uid, open_only=True) == []
        assert queries.fault_episodes(conn, vehicle_id="V1", start=160.0) == []
        assert len(queries.fault_episodes(conn, vehicle_id="V1", start=120.0, end=130.0)) == 1
        assert queries.fault_counts(conn, uid)["OVF"]["episodes"] == 1
        assert queries.latest_values(conn, uid) == {
            "voltages": {"ts": 200.0, "fields": {"v12": 13.1}}
        }
        unit = queries.get_unit(conn, uid)
        assert unit is not None
        assert (unit["first_seen"], unit["last_seen"], unit["model"]) == (50.0, 200.0, "EQ8001")
        assert queries.list_vehicles(conn)[0]["units"] == 1


def test_retention_prunes_in_batches(engine: Engine) -> None:
    now = 1_700_000_000.0
    old = [
        {"ts": now - 40 * DAY_S + i, "v12": 12.0, "v24": 24.0, "i12": 0.0, "i24": 0.0}
        for i in range(250)
    ]
    new = [
        {"ts": now - DAY_S + i, "v12": 13.0, "v24": 26.0, "i12": 0.0, "i24": 0.0} for i in range(50)
    ]
    _write(engine, _batch(old + new))
    result = prune(engine, raw_days=30, rollup_days=365, now=now, batch_rows=100)
    assert result.deleted["measurements"] == 250
    assert result.batches >= 3
    with engine.connect() as conn:
        uid = queries.unit_id_of(conn, *UNIT)
        assert uid is not None
        assert len(queries.series(conn, uid, "v12", 0, 2e9)) == 50
        # Rollups outlive raw rows.
        assert queries.series(conn, uid, "v12", 0, 2e9, "1d")[0]["count"] == 250
    result = prune(engine, raw_days=30, rollup_days=10, now=now, batch_rows=100)
    with engine.connect() as conn:
        assert all(
            b["ts"] >= now - 10 * DAY_S for b in queries.series(conn, uid, "v12", 0, 2e9, "1m")
        )


def test_a_prune_asked_to_stop_ends_before_its_next_transaction(engine: Engine) -> None:
    """The gateway's stop tells a running prune to end (a cancel does not stop its thread):
    it ends after the transaction at hand, runs nothing more, and the next prune goes on."""
    now = 1_700_000_000.0
    old = [
        {"ts": now - 40 * DAY_S + i, "v12": 12.0, "v24": 24.0, "i12": 0.0, "i24": 0.0}
        for i in range(250)
    ]
    _write(engine, _batch(old))
    stop = threading.Event()
    after_stop: list[str] = []

    @event.listens_for(engine, "before_cursor_execute")
    def _look(_c: Any, _cur: Any, statement: str, *_: Any) -> None:
        if stop.is_set():
            after_stop.append(statement)
        elif statement.lstrip().upper().startswith("DELETE"):
            stop.set()  # the stop comes during the first batch's transaction

    result = prune(engine, raw_days=30, rollup_days=365, now=now, batch_rows=100, stop=stop)
    event.remove(engine, "before_cursor_execute", _look)
    assert result.stopped and result.deleted == {"measurements": 100}, result
    # The first batch's DELETE and commit, the partitions' lock given back (PostgreSQL);
    # nothing of a next batch or table.
    assert not [
        s
        for s in after_stop
        if s.lstrip().upper().startswith(("SELECT", "DELETE")) and "pg_advisory_unlock" not in s
    ], after_stop
    rest = prune(engine, raw_days=30, rollup_days=365, now=now, batch_rows=100)
    assert not rest.stopped and rest.deleted["measurements"] == 150


def test_retention_prunes_the_finished_delivery_log_but_never_the_outbox(engine: Engine) -> None:
    now = 1_700_000_000.0
    hooks: Table = Webhook.__table__  # type: ignore[assignment]
    deliveries: Table = WebhookDelivery.__table__  # type: ignore[assignment]
    with engine.begin() as conn:
        conn.execute(
            insert(hooks).values(
                id=1, name="ops", url="http://127.0.0.1:9/", secret="s", format="json",
                enabled=True, created_at=now, updated_at=now,
            )
        )  # fmt: skip
        for event_id, (state, age_days) in enumerate(
            [("delivered", 20), ("failed", 20), ("pending", 20), ("delivered", 1)], start=1
        ):
            created = now - age_days * DAY_S
            conn.execute(
                insert(deliveries).values(
                    webhook_id=1, event_id=event_id, kind="raised", state=state, attempts=1,
                    created_at=created, next_attempt_at=created,
                )
            )  # fmt: skip
    result = prune(engine, raw_days=5, rollup_days=10, now=now)
    assert result.deleted["webhook_deliveries"] == 2
    with engine.connect() as conn:
        left = conn.execute(select(deliveries.c.event_id).order_by(deliveries.c.event_id))
        assert list(left.scalars()) == [3, 4]  # the old pending one and the recent one


def test_sqlite_engine_creates_file_in_wal(tmp_path: Any) -> None:
    engine = create_engine(f"sqlite:///{tmp_path / 'x.db'}")
    with engine.connect() as conn:
        assert conn.exec_driver_sql("PRAGMA journal_mode").scalar() == "wal"
        assert conn.exec_driver_sql("PRAGMA foreign_keys").scalar() == 1
    engine.dispose()
