"""The writer's journal keeps its on-disk format: a journal left by an earlier version (rows
pickled as `(kind, key, payload)` tuples of plain data) replays after an upgrade, and what
this version writes reads back as the same tuples the earlier one wrote."""

from __future__ import annotations

import io
import pickle
import sqlite3
from pathlib import Path

from sqlalchemy import text

from eqgw.config import WriterSettings
from eqgw.ingest.journal import RowJournal, _dumps, _RowsUnpickler
from eqgw.ingest.rows import RowKind, from_tuple
from eqgw.ingest.writer import BatchedWriter
from eqgw.store.engine import create_engine
from eqgw.store.migrate import upgrade_engine
from tests.db_helpers import archived_frames

UNIT = ("V1/can0", 30)
FLAGS = {"ovf": "active", "uvf": "inactive"}
EPISODE = {
    "fault": "OVF",
    "spn": 168,
    "fmi": 0,
    "source": "dm1+status",
    "state": "active",
    "started_at": 1000.0,
    "last_seen_at": 1003.0,
    "ended_at": None,
    "ended_by": None,
    "occurrence_count": 2,
}


def _old_rows() -> list[tuple[object, object, object]]:
    """One row of every kind, shaped as the writer took them before rows had types (the
    list in app/ingest/writer.py of that version): (kind, key, payload)."""
    return [
        ("vehicle", "V1", {"id": "V1", "name": "Bus one", "depot": "North"}),
        ("unit", UNIT, "V1"),
        ("unit_owner", UNIT, {"since": 999.0, "name": "0x00000000001E0001"}),
        ("unit_info", UNIT, {"ts": 1000.5, "series": 80, "model": "EQ8001"}),
        ("unit_info", UNIT, {"ts": 1000.6, "series": 80, "software_id": "SW 1.2"}),
        ("measurements", UNIT, {"ts": 1000.0, "v12": 12.6, "v24": 25.2, "i12": 1.0, "i24": None}),
        ("measurements", UNIT, {"ts": 1003.0, "v12": 12.7, "v24": 25.3, "i12": 1.5, "i24": 2.0}),
        (
            "battery_states",
            UNIT,
            {
                "ts": 1001.0,
                "idx": 1,
                "battery": "12v",
                "soc": None,
                "soc_achievable": 90.5,
                "soh": 99.0,
                "dod": None,
                "runtime_min": 120.0,
                "runtime_temp_adj_min": None,
                "major_12v": None,
                "minor_12v": None,
                "major_24v": None,
                "minor_24v": None,
                "temperature_c": None,
                "temperature_raw": None,
            },
        ),
        ("status_changes", UNIT, {"ts": 1000.0, "flags": FLAGS, "changed": ["ovf", "uvf"]}),
        (
            "dm1_snapshots",
            UNIT,
            {
                "ts": 1000.0,
                "lamps": {"mil": 0, "rsl": 0, "awl": 1, "pl": 0},
                "dtcs": [{"spn": 168, "fmi": 0, "oc": 1, "cm": 0, "code": "OVF"}],
            },
        ),
        (
            "messages",
            UNIT,
            {"ts": 1000.5, "name": "component_id", "idx": 0, "fields": {"text": "EQ8001"}},
        ),
        ("raw_frames", UNIT, {"ts": 1000.0, "can_id": 0x18FFD61E, "seq": 0, "data": b"\x01\x02"}),
        ("raw_frames", UNIT, {"ts": 1000.0, "can_id": 0x18FFD61E, "seq": 1, "data": b"\x03"}),
        ("episode", (UNIT, "OVF", 1000.0), EPISODE),
        ("live", (UNIT, "status"), {"ts": 1003.0, "fields": FLAGS}),
        ("seen", UNIT, (1000.0, 1003.0)),
        ("seen", UNIT, (998.0, 1001.0)),
    ]


def test_every_row_kind_reads_back_and_writes_the_same_bytes() -> None:
    old = _old_rows()
    assert {RowKind(kind) for kind, _, _ in old} == set(RowKind)
    rows = [from_tuple(item) for item in old]
    assert [row.as_tuple() for row in rows] == old
    # What this version writes, the earlier version's reader (plain data only, no class)
    # reads as the tuples it wrote itself: a downgrade replays the journal too.
    assert _RowsUnpickler(io.BytesIO(_dumps(rows))).load() == old


def test_a_journal_written_by_the_earlier_version_replays(db_url: str, tmp_path: Path) -> None:
    engine = create_engine(db_url)
    upgrade_engine(engine)
    # The journal file as the earlier version left it: its schema, and one entry of rows
    # pickled as plain tuples.
    journal = RowJournal.open(tmp_path, db_url)
    path = journal.path
    journal.close(remove=False)
    old = _old_rows()
    with sqlite3.connect(path) as db:
        db.execute(
            "INSERT INTO chunks (rows, data) VALUES (?, ?)",
            (len(old), pickle.dumps(old, protocol=5)),
        )
    db.close()

    journal = RowJournal.open(tmp_path, db_url)
    assert journal.inherited_rows == len(old)
    writer = BatchedWriter(engine, WriterSettings(flush_ms=20), journal=journal)
    writer.start()
    try:
        assert writer.wait_replayed(30)
        st = writer.status()
        assert st.replayed_rows == len(old) and st.journal_rows == 0 and st.rejected_rows == 0
    finally:
        assert writer.stop(10) == 0
    assert not path.exists()  # replayed, empty, removed

    with engine.connect() as conn:

        def all_of(sql: str) -> list[tuple[object, ...]]:
            return [tuple(r) for r in conn.execute(text(sql))]

        assert all_of("SELECT id, name, depot FROM vehicles") == [("V1", "Bus one", "North")]
        assert all_of(
            "SELECT bus, sa, vehicle_id, name, series, model, software_id, first_seen, last_seen "
            "FROM units"
        ) == [("V1/can0", 30, "V1", "0x00000000001E0001", 80, "EQ8001", "SW 1.2", 998.0, 1003.0)]
        assert all_of("SELECT since, name FROM unit_owners") == [(999.0, "0x00000000001E0001")]
        assert all_of("SELECT ts, v12, v24, i12, i24 FROM measurements ORDER BY ts") == [
            (1000.0, 12.6, 25.2, 1.0, None),
            (1003.0, 12.7, 25.3, 1.5, 2.0),
        ]
        assert all_of("SELECT ts, idx, battery, soc_achievable, soh FROM battery_states") == [
            (1001.0, 1, "12v", 90.5, 99.0)
        ]
        assert len(all_of("SELECT ts FROM status_changes")) == 1
        assert len(all_of("SELECT ts FROM dm1_snapshots")) == 1
        assert all_of("SELECT ts, name, idx FROM messages") == [(1000.5, "component_id", 0)]
        assert all_of(
            "SELECT fault, state, started_at, last_seen_at, occurrence_count FROM fault_episodes"
        ) == [("OVF", "active", 1000.0, 1003.0, 2)]
        assert all_of("SELECT name, ts FROM live_state") == [("status", 1003.0)]
        assert len(all_of("SELECT bucket_ts FROM rollups")) > 0
    engine.dispose()
    frames = archived_frames(db_url)
    assert sorted((f.ts, f.can_id, f.seq, bytes(f.data)) for f in frames) == [
        (1000.0, 0x18FFD61E, 0, b"\x01\x02"),
        (1000.0, 0x18FFD61E, 1, b"\x03"),
    ]
