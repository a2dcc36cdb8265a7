"""The raw archive (eqgw.store.archive): blocks read back bit for bit, writes idempotent
before and after a minute is packed, late frames merged, packing in bounded transactions,
retention, and the migration of a populated raw_frames table, on SQLite and PostgreSQL."""

from __future__ import annotations

import struct
import time
from typing import Any

import pytest
from alembic.script import ScriptDirectory
from hypothesis import given, settings
from hypothesis import strategies as st
from sqlalchemy import Engine, inspect, text

from eqgw.ingest.rows import RawFrameRow, Row, UnitRow, VehicleRow
from eqgw.ingest.writer import BatchedWriter, build_batch
from eqgw.store import archive
from eqgw.store.archive import (
    BLOCK_S,
    CAN_EFF_FLAG,
    ArchiveError,
    Frame,
    block_start,
    compact,
    count_frames,
    pack_block,
    read_frames,
    unpack_block,
    word_of,
)
from eqgw.store.engine import create_engine
from eqgw.store.migrate import alembic_config, upgrade_engine
from eqgw.store.retention import prune
from eqgw.store.writes import load_unit_ids, write_batch

UNIT = ("V1/can0", 30)
OTHER = ("V1/can0", 31)
T0 = 1_763_700_000.0  # a minute boundary (29,395,000 minutes)
ID = 0x18FFD41E


def _bits(ts: float) -> bytes:
    return struct.pack("<d", ts)


frames_st = st.lists(
    st.builds(
        Frame,
        ts=st.one_of(
            st.floats(allow_nan=False, allow_infinity=False),
            st.sampled_from([T0, T0 + 0.000001, T0 + 59.999999, 0.0, 5e-324]),
        ),
        word=st.integers(0, 0xFFFFFFFF),
        seq=st.integers(0, 0x7FFF),
        data=st.binary(max_size=64),
    ),
    max_size=200,
    unique_by=lambda f: (_bits(f.ts), f.word, f.seq),
).filter(lambda fs: len({f[:3] for f in fs}) == len(fs))  # -0.0 and 0.0 are one key


@settings(max_examples=300, deadline=None)
@given(frames_st)
def test_a_block_reads_back_bit_for_bit(frames: list[Frame]) -> None:
    got = unpack_block(pack_block(frames))
    want = sorted(frames)
    assert [(_bits(f.ts), f.word, f.seq, f.data) for f in got] == [
        (_bits(f.ts), f.word, f.seq, f.data) for f in want
    ]


def test_frames_of_one_time_and_identifier_are_all_kept() -> None:
    """Duplicates (same time, identifier; seq 0 and 1) stay; a merge adds only new keys."""
    a = Frame(T0 + 1.5, word_of(ID), 0, b"\x01")
    b = Frame(T0 + 1.5, word_of(ID), 1, b"\x02")
    c = Frame(T0 + 1.5, word_of(0x123, extended=False), 0, b"")
    block = unpack_block(pack_block([b, c, a]))
    assert block == sorted([a, b, c]) and len(block) == 3
    merged, added = archive.merge_frames(block, [a, b, Frame(T0 + 2, word_of(ID), 0, b"\x03")])
    assert added == 1 and len(merged) == 4
    assert archive.merge_frames(merged, merged) == (merged, 0)
    standard = next(f for f in block if f.word == c.word)
    assert standard.can_id == 0x123 and not standard.is_extended
    assert a.can_id == ID and a.is_extended and not a.is_remote and not a.is_error


def test_block_starts() -> None:
    for ts in (T0, T0 + 59.99999999, T0 - 1e-6, 0.0, 59.999999999999, 1e9 + 1e-7):
        start = block_start(ts)
        assert start <= ts < start + BLOCK_S and start % BLOCK_S == 0


@pytest.mark.parametrize(
    "damage",
    [
        lambda blob: blob[: len(blob) // 2],  # cut short
        lambda blob: b"not zlib at all",
        lambda blob: __import__("zlib").compress(b"\x07" + b"\x00" * 20),  # a future layout
        lambda blob: __import__("zlib").compress(__import__("zlib").decompress(blob) + b"x"),
    ],
)
def test_a_damaged_block_is_an_archive_error(damage: Any) -> None:
    blob = pack_block([Frame(T0 + i, word_of(ID), 0, bytes([i] * 8)) for i in range(10)])
    with pytest.raises(ArchiveError):
        unpack_block(damage(blob))


# -- through the writer's batches ---------------------------------------------------------


def _items(frames: list[tuple[tuple[str, int], float, int, int, bytes]]) -> list[Row]:
    items: list[Row] = [VehicleRow("V1", {"id": "V1", "name": "V1", "depot": None})]
    items += [UnitRow(key, "V1") for key in {f[0] for f in frames}]
    for key, ts, can_id, seq, data in frames:
        items.append(RawFrameRow(key, {"ts": ts, "can_id": can_id, "seq": seq, "data": data}))
    return items


def _write(engine: Engine, items: list[Row]) -> dict[str, int]:
    w = engine.execution_options(sqlite_begin="IMMEDIATE")
    with w.begin() as conn:
        result = write_batch(conn, build_batch(items), load_unit_ids(conn))
    return result.inserted


def _archived(engine: Engine) -> list[tuple[int, bytes, int, int, bytes]]:
    """(unit id, ts bits, identifier word, seq, data) of every archived frame, in order."""
    with engine.connect() as conn:
        uids = list(load_unit_ids(conn).values())
        return [(u, _bits(f.ts), f.word, f.seq, f.data) for u, f in read_frames(conn, uids)]


def _table_rows(engine: Engine, table: str) -> int:
    with engine.connect() as conn:
        return int(conn.execute(text(f"SELECT count(*) FROM {table}")).scalar_one())


def _frames(n: int, start: float = T0, step: float = 0.5) -> list[Any]:
    """`n` frames of UNIT (every fifth also a second frame of its time and id, seq 1) and
    some of OTHER, full-precision times over several minutes."""
    out: list[Any] = []
    for i in range(n):
        ts = start + i * step + 1e-7 * (i % 7)
        out.append((UNIT, ts, ID + (i % 3 << 8), 0, bytes([i % 256]) * (i % 9)))
        if i % 5 == 0:
            out.append((UNIT, ts, ID + (i % 3 << 8), 1, b"dup"))
        if i % 4 == 0:
            out.append((OTHER, ts, ID + 1, 0, b"\xff" * 8))
    return out


def test_writes_add_nothing_again_before_and_after_packing(engine: Engine) -> None:
    frames = _frames(400)  # 200 s: four minutes
    assert _write(engine, _items(frames))["raw_frames"] == len(frames)
    recent = _archived(engine)
    assert len(recent) == len(frames) == _table_rows(engine, "raw_recent")
    assert _write(engine, _items(frames))["raw_frames"] == 0  # a retried batch, not packed yet
    assert compact(engine, before=T0 + 1e6) == len(frames)
    assert _table_rows(engine, "raw_recent") == 0
    assert _table_rows(engine, "raw_blocks") == 2 * 4  # two units, four minutes
    assert _archived(engine) == recent  # bit for bit, in the same order
    with engine.connect() as conn:
        blobs = conn.execute(text("SELECT data FROM raw_blocks ORDER BY unit_id, ts")).all()
    # A replay after packing: every frame found in its block, nothing added or rewritten.
    assert _write(engine, _items(frames))["raw_frames"] == 0
    assert _table_rows(engine, "raw_recent") == 0
    with engine.connect() as conn:
        assert conn.execute(text("SELECT data FROM raw_blocks ORDER BY unit_id, ts")).all() == blobs
        assert count_frames(conn) == len(frames)
    # A frame late for its (packed) minute joins the block; with it, a frame of a new minute.
    late = [(UNIT, T0 + 30.25, ID, 0, b"late"), (UNIT, T0 + 1000.0, ID, 0, b"new")]
    assert _write(engine, _items(late))["raw_frames"] == 2
    assert _table_rows(engine, "raw_recent") == 1  # only the new minute's frame waits
    got = _archived(engine)
    assert len(got) == len(frames) + 2
    with engine.connect() as conn:
        uid = load_unit_ids(conn)[UNIT]
    assert (uid, _bits(T0 + 30.25), ID | CAN_EFF_FLAG, 0, b"late") in got
    assert _write(engine, _items(late))["raw_frames"] == 0


def test_packing_in_small_transactions_loses_nothing(engine: Engine) -> None:
    frames = _frames(300)
    _write(engine, _items(frames))
    want = _archived(engine)
    # A few frames a transaction: minutes are cut at the limit and packed over several turns.
    with engine.begin() as conn:
        n, more = archive.compact_once(conn, block_start(T0 + 1e6), 7)
    assert 0 < n <= 7 and more
    assert compact(engine, before=T0 + 1e6, max_frames=50) == len(frames) - n
    assert _table_rows(engine, "raw_recent") == 0
    assert _archived(engine) == want


def test_packing_leaves_minutes_that_are_not_due(engine: Engine) -> None:
    frames = _frames(240)  # T0 .. T0 + 120 s
    _write(engine, _items(frames))
    packed = compact(engine, before=T0 + 60.0)  # only the first minute has ended
    assert packed == sum(1 for f in frames if f[1] < T0 + 60.0)
    assert _table_rows(engine, "raw_recent") == len(frames) - packed
    assert compact(engine, before=T0 + 60.0) == 0
    assert len(_archived(engine)) == len(frames)


def test_a_frame_both_packed_and_waiting_is_read_once(engine: Engine) -> None:
    """Two gateways racing (one packs a minute while the other, which saw no block yet,
    adds the same frame to raw_recent): readers give the frame once; the next packing
    folds the copy into the block."""
    frames = _frames(100)
    _write(engine, _items(frames))
    compact(engine, before=T0 + 1e6)
    want = _archived(engine)
    with engine.begin() as conn:
        uid = load_unit_ids(conn)[UNIT]
        conn.execute(
            text("INSERT INTO raw_recent VALUES (:u, :ts, :c, 0, :d)"),
            {"u": uid, "ts": frames[0][1], "c": frames[0][2] | CAN_EFF_FLAG, "d": frames[0][4]},
        )
    assert _archived(engine) == want
    assert compact(engine, before=T0 + 1e6) == 1
    assert _table_rows(engine, "raw_recent") == 0
    assert _archived(engine) == want


def test_the_writer_packs_due_minutes_on_its_own(engine: Engine) -> None:
    frames = _frames(200)
    writer = BatchedWriter(engine)
    writer.start()
    try:
        assert writer.put(_items(frames), timeout=30)
        assert writer.flush(timeout=30)
        deadline = time.monotonic() + 60
        while writer.status().compacted_frames < len(frames):
            assert time.monotonic() < deadline, writer.status()
            time.sleep(0.1)
    finally:
        writer.stop()
    assert _table_rows(engine, "raw_recent") == 0
    assert len(_archived(engine)) == len(frames)


def test_retention_drops_blocks_past_the_cutoff(engine: Engine) -> None:
    old = _frames(20, start=T0)
    new = _frames(20, start=T0 + 10 * 86400)
    _write(engine, _items(old + new))
    compact(engine, before=T0 + 1e7)
    now = T0 + 10 * 86400 + 3600
    result = prune(engine, raw_days=5, rollup_days=30, now=now)
    assert result.deleted["raw_blocks"] == 2  # the old minute of each unit
    got = _archived(engine)
    assert len(got) == len(new)
    assert all(struct.unpack("<d", f[1])[0] >= T0 + 10 * 86400 for f in got)


# -- the migration of a populated raw_frames table ----------------------------------------


# The revision before the archive was packed (whatever the migrations chain it to).
BEFORE = str(
    ScriptDirectory.from_config(alembic_config()).get_revision("0012_rawblocks").down_revision
)


def _populate_raw_frames(engine: Engine, n: int) -> list[tuple[int, float, int, int, bytes]]:
    """`n` raw_frames rows over two units (as the revision before keeps them), frames of one time
    and identifier among them (seq 1)."""
    rows: list[tuple[int, float, int, int, bytes]] = []
    with engine.begin() as conn:
        conn.execute(text("INSERT INTO vehicles (id, name) VALUES ('V1', 'V1')"))
        for sa in (30, 31):
            conn.execute(
                text("INSERT INTO units (bus, sa, vehicle_id) VALUES ('V1/can0', :sa, 'V1')"),
                {"sa": sa},
            )
        uids = [int(u) for u in conn.execute(text("SELECT id FROM units ORDER BY sa")).scalars()]
        for i in range(n):
            uid = uids[i % 2]
            ts = T0 + (i // 2) * 0.37 + 1e-7 * (i % 11)
            rows.append((uid, ts, ID + (i % 5), 0, bytes([i % 251]) * (i % 9)))
            if i % 17 == 0:
                rows.append((uid, ts, ID + (i % 5), 1, b"second"))
        insert = (
            "INSERT INTO raw_frames (unit_id, ts, can_id, seq, data) VALUES (:u, :t, :c, :s, :d)"
        )
        conn.execute(
            text(insert), [{"u": u, "t": t, "c": c, "s": s, "d": d} for u, t, c, s, d in rows]
        )
    return rows


def test_migration_moves_every_raw_frame_into_blocks_and_back(empty_db_url: str) -> None:
    from alembic import command

    engine = create_engine(empty_db_url)
    try:
        upgrade_engine(engine, BEFORE)
        rows = _populate_raw_frames(engine, 3000)
        # Up to this migration and back over it alone (later ones have their own tests).
        upgrade_engine(engine, "0012_rawblocks")
        assert "raw_frames" not in inspect(engine).get_table_names()
        assert _table_rows(engine, "raw_recent") == 0
        with engine.connect() as conn:
            got = read_frames(conn, sorted({r[0] for r in rows}))
            assert count_frames(conn) == len(rows)
        want = sorted(rows, key=lambda r: (r[1], r[0], r[2], r[3]))
        assert [(u, _bits(f.ts), f.word, f.seq, f.data) for u, f in got] == [
            (u, _bits(t), c | CAN_EFF_FLAG, s, d) for u, t, c, s, d in want
        ]
        # And back: the downgrade unpacks every block into raw_frames.
        command.downgrade(alembic_config(empty_db_url), BEFORE)
        with engine.connect() as conn:
            back = conn.execute(text("SELECT unit_id, ts, can_id, seq, data FROM raw_frames")).all()
        assert sorted((u, _bits(t), c, s, bytes(d)) for u, t, c, s, d in back) == sorted(
            (u, _bits(t), c, s, d) for u, t, c, s, d in rows
        )
        assert "raw_blocks" not in inspect(engine).get_table_names()
    finally:
        engine.dispose()
