"""Packed measurements and battery states (eqgw.store.packed): blocks read back bit for bit,
reads identical before and after packing, writes idempotent before and after an hour is
packed, late rows merged, the writer packing on its own, retention, and the migration of
populated tables up and down, on SQLite and PostgreSQL."""

from __future__ import annotations

import math
import struct
import time
from typing import Any

import pytest
from alembic.script import ScriptDirectory
from hypothesis import given, settings
from hypothesis import strategies as st
from sqlalchemy import Engine, inspect, text

from eqgw.ingest.rows import from_tuple
from eqgw.ingest.writer import BatchedWriter
from eqgw.store import packed, queries
from eqgw.store.engine import create_engine
from eqgw.store.migrate import alembic_config, upgrade_engine
from eqgw.store.models import ROLLUP_METRICS
from eqgw.store.packed import (
    BATTERY_STATES,
    MEASUREMENTS,
    PackedError,
    compact,
    pack_rows,
    unpack_rows,
)
from eqgw.store.retention import prune
from eqgw.store.writes import Batch, load_unit_ids, write_batch

UNIT = ("V1/can0", 30)
OTHER = ("V1/can0", 31)
T0 = 1_763_697_600.0  # an hour boundary
# Every sample the rollups counted, all metrics and widths.
_SAMPLES = " + ".join(f"coalesce(sum({m}_n), 0)" for m in ROLLUP_METRICS)
NOW = T0 + 10 * 86400  # the clock of these tests: everything written is days old


def _bits(v: Any) -> Any:
    return struct.pack("<d", v) if isinstance(v, float) else v


def _same(a: list[Any], b: list[Any]) -> bool:
    """Row lists equal value for value, floats to the bit (NaN equal to itself)."""
    return [tuple(map(_bits, r)) for r in a] == [tuple(map(_bits, r)) for r in b]


# -- the block format ---------------------------------------------------------------------

_EXTREMES = [0.0, -0.0, math.nan, math.inf, -math.inf, 5e-324, 1.7976931348623157e308, -1e-300]
floats = st.one_of(
    st.none(),
    st.floats(allow_nan=True, allow_infinity=True),
    st.sampled_from(_EXTREMES),
    st.integers(0, 0xFAFF).map(lambda k: round(k * 0.005, 3)),  # as the decoder makes them
    st.integers(0, 0xFAFF).map(lambda k: round(k * 0.05 - 1600.0, 2)),
)
ints = st.one_of(st.none(), st.integers(-(2**63), 2**63 - 1), st.integers(0, 255))
times = st.one_of(
    st.floats(allow_nan=False, allow_infinity=False),
    st.integers(0, 10**6).map(lambda i: T0 + i * 0.001),
    st.sampled_from([T0, T0 + 3599.999999, -0.0, 5e-324]),
)


@settings(max_examples=100, deadline=None)
@given(st.lists(st.tuples(times, floats, floats, floats, floats), max_size=60))
def test_measurement_blocks_read_back_bit_for_bit(rows: list[Any]) -> None:
    unique = list({_bits(r[0]) if r[0] != 0 else 0: r for r in rows}.values())
    got = unpack_rows(MEASUREMENTS, pack_rows(MEASUREMENTS, unique))
    assert _same(got, sorted(unique, key=lambda r: r[0]))


@settings(max_examples=50, deadline=None)
@given(
    st.lists(
        st.tuples(
            times,
            st.integers(1, 5),
            st.sampled_from([None, "12v", "24v", "x" * 8, "é"]),
            *([floats] * 6),
            *([ints] * 4),
            floats,
            ints,
        ),
        max_size=30,
    )
)
def test_battery_blocks_read_back_bit_for_bit(rows: list[Any]) -> None:
    unique = list({(_bits(r[0]) if r[0] != 0 else 0, r[1]): r for r in rows}.values())
    got = unpack_rows(BATTERY_STATES, pack_rows(BATTERY_STATES, unique))
    assert _same(got, sorted(unique, key=lambda r: (r[0], r[1])))


def test_fixed_point_values_pack_small() -> None:
    """A day-like hour: 1,200 voltages frames at 3 s, 16-bit fields (0.005 V, 0.05 A)."""
    rows = [
        (
            T0 + 3 * i + 0.001 * (i % 7),
            round((2700 + i % 13) * 0.005, 3),
            round((5500 + i % 17) * 0.005, 3),
            round((32000 + i % 41) * 0.05 - 1600.0, 2),
            None,
        )
        for i in range(1200)
    ]
    blob = pack_rows(MEASUREMENTS, rows)
    assert len(blob) < 1200 * 4
    assert _same(unpack_rows(MEASUREMENTS, blob), rows)


@pytest.mark.parametrize(
    "damage",
    [lambda b: b[:-3], lambda b: b"x" + b, lambda b: __import__("zlib").compress(b"\x09" * 9)],
)
def test_a_damaged_block_is_a_packed_error(damage: Any) -> None:
    blob = pack_rows(MEASUREMENTS, [(T0, 1.0, 2.0, None, None)])
    with pytest.raises(PackedError):
        unpack_rows(MEASUREMENTS, damage(blob))


# -- the database -------------------------------------------------------------------------


def _m(ts: float, i: int) -> dict[str, Any]:
    return {
        "ts": ts,
        "v12": round((2700 + i % 13) * 0.005, 3),
        "v24": round((5500 + i % 17) * 0.005, 3),
        "i12": None if i % 11 == 0 else round((32000 + i % 41) * 0.05 - 1600.0, 2),
        "i24": 1e300 if i == 5 else -0.0 if i == 6 else round(i * 0.05 - 1600.0, 2),
    }


def _b(ts: float, i: int) -> dict[str, Any]:
    idx = 1 + i % 5
    row: dict[str, Any] = dict.fromkeys(
        [c for c in BATTERY_STATES.columns if c not in ("ts", "idx")], None
    )
    row.update(ts=ts, idx=idx, battery={1: "12v", 2: "12v", 3: "24v", 4: "24v"}.get(idx))
    if idx in (1, 3):
        row.update(soc_achievable=round(i % 1000 * 0.1, 1), soh=99.5, runtime_min=i * 0.5)
    elif idx in (2, 4):
        row.update(soc=round(i % 1000 * 0.1, 1), dod=12.3, runtime_temp_adj_min=i * 0.5)
    else:
        row.update(major_12v=i % 4, minor_12v=2, major_24v=1, minor_24v=0)
        row.update(temperature_c=round((30250 + i % 9) * 0.1 - 3000.0, 1))
        row.update(temperature_raw=30250 + i % 9)
    return row


def _batch(
    measurements: list[tuple[Any, dict[str, Any]]], battery: list[tuple[Any, dict[str, Any]]]
) -> Batch:
    b = Batch()
    b.vehicles = {"V1": {"id": "V1", "name": "V1", "depot": None}}
    b.units = {UNIT: "V1", OTHER: "V1"}
    b.measurements = measurements
    b.battery_states = battery
    for key, row in [*measurements, *battery]:
        seen = b.seen.setdefault(key, [row["ts"], row["ts"]])
        seen[0], seen[1] = min(seen[0], row["ts"]), max(seen[1], row["ts"])
    return b


def _write(engine: Engine, b: Batch) -> dict[str, int]:
    with engine.begin() as conn:
        return write_batch(conn, b, load_unit_ids(conn)).inserted


def _day(hours: float, start: float = T0) -> Batch:
    """Measurements every 3 s and battery states every 5 s over `hours` of UNIT (and a
    sparser OTHER), with the odd null, -0.0 and extreme value."""
    n = int(hours * 1200)
    m = [(UNIT, _m(start + 3 * i + 0.001 * (i % 3), i)) for i in range(n)]
    m += [(OTHER, _m(start + 30 * i, i)) for i in range(n // 10)]
    b = [(UNIT, _b(start + 5 * i, i)) for i in range(int(hours * 720))]
    return _batch(m, b)


METRICS = ["v12", "v24", "i12", "i24", "soc_12v", "soh_24v", "dod_12v", "temperature_c"]


def _reads(engine: Engine) -> dict[str, Any]:
    """Every raw read the API makes (series at raw resolution, with and without a limit, and
    rollups), for both units."""
    out: dict[str, Any] = {}
    with engine.connect() as conn:
        ids = load_unit_ids(conn)
        for key in (UNIT, OTHER):
            for metric in METRICS:
                for lo, hi, limit in (
                    (T0 - 10, T0 + 86400, None),
                    (T0 + 1800, T0 + 5000, None),
                    (T0 + 3500, T0 + 9000, 50),
                    (T0, T0 + 86400, 3000),
                ):
                    pts = queries.series(conn, ids[key], metric, lo, hi, limit=limit)
                    out[f"{key}/{metric}/{lo}/{limit}"] = [(p["ts"], p["value"]) for p in pts]
            out[f"{key}/1m"] = queries.series_many(conn, ids[key], METRICS, T0, T0 + 86400, "1m")
        out["counts"] = {
            k: v
            for k, v in queries.row_counts(conn).items()
            if k in ("measurements", "battery_states")
        }
    return out


def _same_reads(a: dict[str, Any], b: dict[str, Any]) -> None:
    assert a.keys() == b.keys()
    for k in a:
        if isinstance(a[k], list):
            assert _same(a[k], b[k]), k
        else:
            assert a[k] == b[k], k


def _rows(engine: Engine, table: str) -> int:
    with engine.connect() as conn:
        return int(conn.execute(text(f"SELECT count(*) FROM {table}")).scalar_one())


def test_reads_are_the_same_before_and_after_packing(engine: Engine) -> None:
    day = _day(5)
    got = _write(engine, day)
    assert got["measurements"] == len(day.measurements)
    before = _reads(engine)
    assert sum(len(v) for v in before.values() if isinstance(v, list)) > 10_000
    # Units last seen just before T0 + 5 h: the hours that ended an hour before are due.
    edge = T0 + 3 * 3600
    moved = compact(engine, now=NOW)
    assert moved == sum(1 for _, r in day.measurements if r["ts"] < edge) + sum(
        1 for _, r in day.battery_states if r["ts"] < edge
    )
    assert _rows(engine, "measurement_blocks") == 3 * 2  # two units, three hours
    assert _rows(engine, "battery_blocks") == 3
    assert compact(engine, now=NOW) == 0  # nothing more is due
    _same_reads(before, _reads(engine))


def test_writes_add_nothing_again_after_packing_and_late_rows_join_their_block(
    engine: Engine,
) -> None:
    day = _day(3)
    _write(engine, day)
    compact(engine, now=NOW)
    want = _reads(engine)
    blocks = _blocks(engine)
    # A replay (a journal written twice, a log replayed): nothing added, no block rewritten.
    again = _write(engine, _day(3))
    assert again["measurements"] == again["battery_states"] == 0
    assert _blocks(engine) == blocks
    _same_reads(want, _reads(engine))
    with engine.connect() as conn:
        rollups_before = conn.execute(text(f"SELECT {_SAMPLES} FROM rollups")).scalar_one()
    # Late rows for a packed hour join its block (and the rollups, once); a row of a new hour
    # goes to the table.
    # (The first hour is packed; T0 is in its block already, with other values.)
    late_m = [(UNIT, _m(T0 + 1.5, 7)), (UNIT, _m(T0, 1)), (UNIT, _m(T0 + 99999, 2))]
    late_b = [(UNIT, _b(T0 + 2.5, 3))]
    got = _write(engine, _batch(late_m, late_b))
    assert got["measurements"] == 2 and got["battery_states"] == 1
    assert _write(engine, _batch(late_m, late_b))["measurements"] == 0
    with engine.connect() as conn:
        rollups_after = conn.execute(text(f"SELECT {_SAMPLES} FROM rollups")).scalar_one()
        uid = load_unit_ids(conn)[UNIT]
        points = queries.series(conn, uid, "v12", T0, T0 + 3)
        assert [p["ts"] for p in points] == [T0, T0 + 1.5]
        assert queries.series(conn, uid, "soc_24v", T0 + 2, T0 + 3)[0]["ts"] == T0 + 2.5
    # Two rows of four metrics, soc and dod of the battery state, each in four bucket widths.
    assert rollups_after - rollups_before == (4 + 4 + 2) * 4
    assert _rows(engine, "measurements") == 1 + sum(
        1 for _, r in day.measurements if r["ts"] >= T0 + 3600
    )


def _blocks(engine: Engine) -> list[Any]:
    with engine.connect() as conn:
        return [
            tuple(r)
            for t in ("measurement_blocks", "battery_blocks")
            for r in conn.execute(text(f"SELECT unit_id, ts, samples, data FROM {t} ORDER BY 1, 2"))
        ]


def test_packing_in_small_transactions_loses_nothing(engine: Engine) -> None:
    _write(engine, _day(4))
    want = _reads(engine)
    with engine.connect() as conn:
        edges = packed.due_edges(conn, NOW)
    uid = load_unit_ids(engine.connect())[UNIT]
    with engine.begin() as conn:
        n, more = packed.compact_once(conn, MEASUREMENTS, uid, edges[uid], 700)
    assert 0 < n <= 700 and more  # an hour cut at the limit is packed whole next time
    compact(engine, now=NOW, max_rows=1500)
    _same_reads(want, _reads(engine))
    assert _rows(engine, "measurement_blocks") == 2 * 2


def test_a_row_both_packed_and_in_its_table_is_read_once(engine: Engine) -> None:
    """Two writers racing: a row in its table and in its block is read once; the next packing
    folds it into the block."""
    day = _day(3)
    _write(engine, day)
    compact(engine, now=NOW)
    want = _reads(engine)
    with engine.begin() as conn:
        uid = load_unit_ids(conn)[UNIT]
        row = day.measurements[0][1]
        conn.execute(
            text("INSERT INTO measurements VALUES (:u, :ts, :v12, :v24, :i12, :i24)"),
            {"u": uid, **row},
        )
    racing = _reads(engine)
    assert racing.pop("counts")["measurements"] == want["counts"]["measurements"] + 1
    _same_reads({k: v for k, v in want.items() if k != "counts"}, racing)
    # A row of a packed hour only in the table (written while the hour was being packed),
    # written again: left to the next packing, not added to the block (nor counted) twice.
    extra = {**row, "ts": T0 + 1.25}
    with engine.begin() as conn:
        conn.execute(
            text("INSERT INTO measurements VALUES (:u, :ts, :v12, :v24, :i12, :i24)"),
            {"u": uid, **extra},
        )
    assert _write(engine, _batch([(UNIT, dict(row)), (UNIT, extra)], []))["measurements"] == 0
    assert compact(engine, now=NOW) == 2
    with engine.connect() as conn:
        got = queries.series(conn, uid, "v12", T0, T0 + 2)
        assert [p["ts"] for p in got] == [T0, T0 + 1.25]
        assert queries.row_counts(conn)["measurements"] == want["counts"]["measurements"] + 1


def test_nothing_is_packed_within_the_horizon_of_the_clock_or_the_unit(engine: Engine) -> None:
    _write(engine, _day(1.9))
    assert compact(engine, now=NOW) == 0  # the unit's newest data is < 2 h after its first
    assert compact(engine, now=T0 + 1800) == 0  # the clock says the data is 30 min old


def test_the_writer_packs_due_hours_on_its_own(engine: Engine) -> None:
    day = _day(3)
    items: list[Any] = [("vehicle", "V1", {"id": "V1", "name": "V1", "depot": None})]
    items += [("unit", UNIT, "V1"), ("unit", OTHER, "V1")]
    items += [("seen", k, v) for k, v in day.seen.items()]
    items += [("measurements", k, r) for k, r in day.measurements]
    items += [("battery_states", k, r) for k, r in day.battery_states]
    want_m = len(day.measurements)
    writer = BatchedWriter(engine)
    writer.start()
    try:
        assert writer.put([from_tuple(i) for i in items], timeout=30)
        assert writer.flush(timeout=30)
        deadline = time.monotonic() + 60
        while _rows(engine, "measurement_blocks") < 2:
            assert time.monotonic() < deadline, writer.status()
            time.sleep(0.2)
    finally:
        writer.stop()
    with engine.connect() as conn:
        assert queries.row_counts(conn)["measurements"] == want_m


def test_retention_drops_blocks_once_past_the_cutoff(engine: Engine) -> None:
    _write(engine, _day(3))
    compact(engine, now=NOW)
    # Cut 30 min into the second hour: the first hour's blocks are all past it and go.
    now = T0 + 5400 + 5 * 86400
    result = prune(engine, raw_days=5, rollup_days=30, now=now)
    assert result.deleted["measurement_blocks"] == 2
    assert result.deleted["battery_blocks"] == 1
    with engine.connect() as conn:
        uid = load_unit_ids(conn)[UNIT]
        first = queries.series(conn, uid, "v12", 0, 1e12, limit=1)[0]["ts"]
    assert T0 + 5400 <= first < T0 + 5400 + 4


def test_eqgw_db_compact(engine: Engine, db_url: str, capsys: pytest.CaptureFixture[str]) -> None:
    from eqgw.cli import main

    _write(engine, _day(3))
    assert main(["db", "compact", "--db", db_url]) == 0
    assert "measurement and battery-state rows" in capsys.readouterr().out
    assert _rows(engine, "measurement_blocks") == 2


# -- the migration of populated tables ----------------------------------------------------

BEFORE = str(
    ScriptDirectory.from_config(alembic_config()).get_revision("0017_packed_series").down_revision
)


def _table(engine: Engine, name: str) -> list[Any]:
    order = "unit_id, ts, idx" if name == "battery_states" else "unit_id, ts"
    with engine.connect() as conn:
        return [tuple(r) for r in conn.execute(text(f"SELECT * FROM {name} ORDER BY {order}"))]


def test_migration_packs_old_rows_and_the_downgrade_restores_them(empty_db_url: str) -> None:
    from alembic import command

    engine = create_engine(empty_db_url)
    try:
        upgrade_engine(engine, BEFORE)
        # Rows written by the revision before (its write path is this one's, minus blocks).
        day = _day(4, start=time.time() - 6 * 3600 - 7200)
        with engine.begin() as conn:
            conn.execute(text("INSERT INTO vehicles (id, name) VALUES ('V1', 'V1')"))
            for bus, sa in (UNIT, OTHER):
                conn.execute(
                    text("INSERT INTO units (bus, sa, vehicle_id) VALUES (:b, :s, 'V1')"),
                    {"b": bus, "s": sa},
                )
            ids = load_unit_ids(conn)
            m = [{"unit_id": ids[k], **r} for k, r in day.measurements]
            conn.execute(text("INSERT INTO measurements VALUES (:unit_id, :ts, :v12, :v24, "
                              ":i12, :i24)"), m)  # fmt: skip
            cols = ", ".join(f":{c}" for c in BATTERY_STATES.columns)
            b = [{"unit_id": ids[k], **r} for k, r in day.battery_states]
            conn.execute(text(f"INSERT INTO battery_states VALUES (:unit_id, {cols})"), b)
            last = max(r["ts"] for _, r in day.measurements)
            conn.execute(text("UPDATE units SET last_seen = :t"), {"t": last})
        rows_m, rows_b = _table(engine, "measurements"), _table(engine, "battery_states")
        upgrade_engine(engine, "0017_packed_series")
        left = _rows(engine, "measurements")
        assert 0 < left < len(rows_m)  # the last hours stay as rows
        assert _rows(engine, "measurement_blocks") > 0 and _rows(engine, "battery_blocks") > 0
        with engine.connect() as conn:
            got = [
                (uid, *r)
                for uid in sorted(ids.values())
                for r in packed.read_rows(conn, MEASUREMENTS, uid, 0, 1e12)
            ]
            assert queries.row_counts(conn)["measurements"] == len(rows_m)
            assert queries.row_counts(conn)["battery_states"] == len(rows_b)
        assert _same(sorted([*got, *_table(engine, "measurements")]), rows_m)
        # And back: every block unpacked into its table.
        command.downgrade(alembic_config(empty_db_url), BEFORE)
        assert _same(_table(engine, "measurements"), rows_m)
        assert _same(_table(engine, "battery_states"), rows_b)
        assert "measurement_blocks" not in inspect(engine).get_table_names()
    finally:
        engine.dispose()
