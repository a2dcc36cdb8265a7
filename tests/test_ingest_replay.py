"""The realistic mixed log replayed into SQLite and PostgreSQL: rows match the decoded records."""

from __future__ import annotations

import json
from collections import Counter, defaultdict
from pathlib import Path
from typing import Any

import pytest
from sqlalchemy import Engine, func, select, text

from eqgw.cli import main
from eqgw.config import Settings
from eqgw.ingest.faults import STATUS_FAULTS, dtc_fault
from eqgw.ingest.replay import ReplayError, parse_vehicle_map, replay_file
from eqgw.store import queries
from eqgw.store.engine import create_engine
from eqgw.store.models import metadata
from tests.db_helpers import archived_in
from tests.fixtures import mixed_log

BUSES = [
    {
        "name": "BUS-101/can0",
        "vehicle_id": "BUS-101",
        "interface": "virtual",
        "channel": "can0",
        "equalizer_sas": [30, 31],
    },
    {"name": "BUS-102/can1", "vehicle_id": "BUS-102", "interface": "virtual", "channel": "can1"},
]
VEHICLES = [
    {"id": "BUS-101", "name": "Bus 101", "depot": "North"},
    {"id": "BUS-102", "name": "Bus 102", "depot": "South"},
]
BUS_OF_CHANNEL = {"can0": "BUS-101/can0", "can1": "BUS-102/can1"}
VMAP = ["can0=BUS-101", "can1=BUS-102"]
EPISODES_SQL = (
    "SELECT unit_id, fault, started_at, ended_at, occurrence_count, state "
    "FROM fault_episodes ORDER BY 1, 2, 3"
)


def _settings(url: str, **kw: Any) -> Settings:
    return Settings(database_url=url, buses=BUSES, vehicles=VEHICLES, **kw)


def _expected() -> list[dict[str, Any]]:
    return [json.loads(line) for line in mixed_log.EXPECTED.read_text().splitlines()]


def _by_unit(
    records: list[dict[str, Any]], name: str
) -> dict[tuple[str, int], list[dict[str, Any]]]:
    out: dict[tuple[str, int], list[dict[str, Any]]] = defaultdict(list)
    for r in records:
        if r["name"] == name:
            out[(BUS_OF_CHANNEL[r["channel"]], r["sa"])].append(r)
    return out


def _unit_ids(engine: Engine) -> dict[tuple[str, int], int]:
    with engine.connect() as conn:
        return {(u["bus"], u["sa"]): u["id"] for u in queries.list_units(conn)}


def _counts(engine: Engine) -> dict[str, int]:
    with engine.connect() as conn:
        return queries.row_counts(conn)


def test_replay_matches_decoded_records(engine: Engine, db_url: str) -> None:
    summary = replay_file(mixed_log.LOG, VMAP, _settings(db_url))
    expected = _expected()
    assert summary.records == len(expected) == 640
    assert summary.writer.pending_rows == 0
    ids = _unit_ids(engine)
    assert set(ids) == {("BUS-101/can0", 30), ("BUS-101/can0", 31), ("BUS-102/can1", 30)}

    with engine.connect() as conn:
        vehicles = {v["id"]: v for v in queries.list_vehicles(conn)}
        assert vehicles["BUS-101"]["name"] == "Bus 101"
        assert vehicles["BUS-101"]["units"] == 2
        units = {(u["bus"], u["sa"]): u for u in queries.list_units(conn)}
        assert units[("BUS-101/can0", 30)]["model"] == "EQ8001"
        assert units[("BUS-102/can1", 30)]["series"] == 70
        assert units[("BUS-101/can0", 31)]["software_id"] is not None

        # Voltages: one row per record, same values.
        for unit, recs in _by_unit(expected, "voltages").items():
            rows = conn.execute(
                text(
                    "SELECT ts, v12, v24, i12, i24 FROM measurements WHERE unit_id = :u ORDER BY ts"
                ),
                {"u": ids[unit]},
            ).all()
            assert [tuple(r) for r in rows] == [
                (r["ts"], *(r["fields"][k] for k in ("v12", "v24", "i12", "i24"))) for r in recs
            ]
        # Battery states: one row per record, each field where the index carries it.
        for unit, recs in _by_unit(expected, "battery_states").items():
            rows = conn.execute(
                text("SELECT * FROM battery_states WHERE unit_id = :u ORDER BY ts, idx"),
                {"u": ids[unit]},
            ).all()
            assert len(rows) == len(recs)
            for row, rec in zip(
                rows, sorted(recs, key=lambda r: (r["ts"], r["fields"]["index"])), strict=True
            ):
                m = row._mapping
                assert m["idx"] == rec["fields"]["index"]
                for key, value in rec["fields"].items():
                    if key in m and key != "index":
                        assert m[key] == value, (key, rec)
        # Status: stored on change only, with the full flag set.
        for unit, recs in _by_unit(expected, "status").items():
            changes, prev = [], None
            for r in recs:
                if r["fields"] != prev:
                    changes.append((r["ts"], r["fields"]))
                prev = r["fields"]
            got = queries.status_history(conn, ids[unit], 0, 2e9)
            assert [(g["ts"], g["flags"]) for g in got] == changes
        # DM1: stored when the content changes.
        for unit, recs in _by_unit(expected, "dm1").items():
            snaps, prev = [], None
            for r in recs:
                content = (r["fields"]["lamps"], r["fields"]["dtcs"])
                if content != prev:
                    snaps.append((r["ts"], *content))
                prev = content
            got = queries.dm1_history(conn, ids[unit], 0, 2e9)
            assert [(g["ts"], g["lamps"], g["dtcs"]) for g in got] == snaps
        # Requests, control and parameters are kept whole with the addressed unit.
        n_messages = conn.execute(
            select(func.count()).select_from(metadata.tables["messages"])
        ).scalar()
        n_expected = sum(
            1
            for r in expected
            if r["name"] in ("component_id", "software_id", "control", "parameters", "request")
        )
        assert n_messages == n_expected
        # Latest values: the last record of each kind.
        latest = queries.latest_values(conn, ids[("BUS-101/can0", 30)])
        last_v = _by_unit(expected, "voltages")[("BUS-101/can0", 30)][-1]
        assert latest["voltages"] == {"ts": last_v["ts"], "fields": last_v["fields"]}
        assert {"battery_states/1", "battery_states/5", "status", "heartbeat", "dm1"} <= set(latest)
        assert units[("BUS-101/can0", 30)]["last_seen"] == max(
            r["ts"] for r in expected if r["channel"] == "can0" and r["sa"] == 30
        )


def test_fault_episodes_match_the_log(engine: Engine, db_url: str) -> None:
    replay_file(mixed_log.LOG, VMAP, _settings(db_url))
    expected = _expected()
    ids = _unit_ids(engine)
    with engine.connect() as conn:
        for unit, uid in ids.items():
            episodes = queries.fault_episodes(conn, uid)
            dm1 = _by_unit(expected, "dm1").get(unit, [])
            status = _by_unit(expected, "status").get(unit, [])
            want_faults = {dtc_fault(d) for r in dm1 for d in r["fields"]["dtcs"]}
            want_faults |= {
                fault
                for r in status
                for flag, fault in STATUS_FAULTS.items()
                if r["fields"].get(flag) == "active"
            }
            assert {e["fault"] for e in episodes} == want_faults, unit
            last_oc = {dtc_fault(d): d["oc"] for r in dm1 for d in r["fields"]["dtcs"]}
            counts = queries.fault_counts(conn, uid)
            for fault, oc in last_oc.items():
                assert counts[fault]["occurrence_count"] == oc
                assert counts[fault]["episodes"] == 1
                newest = next(e for e in episodes if e["fault"] == fault)
                assert newest["occurrence_count"] == oc
        unit = ids[("BUS-101/can0", 30)]
        by_fault = {e["fault"]: e for e in queries.fault_episodes(conn, unit)}
        # OVF and EQFLT disappear from the DM1 at 40.9 s; UVF is listed 50.92..59.92 s.
        assert (by_fault["OVF"]["started_at"], by_fault["OVF"]["ended_at"]) == (
            mixed_log.START + 31.54,
            mixed_log.START + 40.9,
        )
        assert by_fault["OVF"]["ended_by"] == "dm1"
        assert (by_fault["UVF"]["started_at"], by_fault["UVF"]["ended_at"]) == (
            mixed_log.START + 50.92,
            mixed_log.START + 60.9,
        )
        assert by_fault["IMB"]["source"] == "dm1+status"
        assert all(e["state"] == "closed" for e in by_fault.values())
        # The log ends while units still talk: the end of a log is not an offline unit.
        assert queries.fault_episodes(conn, fault="OFFLINE") == []


def test_replay_twice_adds_nothing(engine: Engine, db_url: str) -> None:
    replay_file(mixed_log.LOG, VMAP, _settings(db_url))
    first = _counts(engine)
    with engine.connect() as conn:
        rollups_first = conn.execute(text("SELECT * FROM rollups ORDER BY 1, 2, 3, 4")).all()
        episodes_first = conn.execute(text(EPISODES_SQL)).all()
    again = replay_file(mixed_log.LOG, VMAP, _settings(db_url))
    assert sum(again.writer.inserted.values()) == 0
    assert _counts(engine) == first
    with engine.connect() as conn:
        assert (
            conn.execute(text("SELECT * FROM rollups ORDER BY 1, 2, 3, 4")).all() == rollups_first
        )
        assert conn.execute(text(EPISODES_SQL)).all() == episodes_first


def test_raw_archive_on_and_off(tmp_path: Path) -> None:
    on = f"sqlite:///{tmp_path / 'on.db'}"
    off = f"sqlite:///{tmp_path / 'off.db'}"
    s_on = replay_file(mixed_log.LOG, VMAP, _settings(on))
    s_off = replay_file(mixed_log.LOG, VMAP, _settings(off, raw_archive=False))
    assert s_on.writer.inserted["raw_frames"] > s_on.records
    assert s_off.writer.inserted.get("raw_frames", 0) == 0


def test_raw_archive_keeps_frames_that_share_a_timestamp(
    engine: Engine, db_url: str, tmp_path: Path
) -> None:
    """A log stamped to the second (as coarse loggers do): frames of one id that share a
    timestamp are each archived, in the order received; a second replay adds nothing."""
    coarse = tmp_path / "coarse.log"
    lines = []
    for line in mixed_log.LOG.read_text().splitlines():
        stamp, rest = line.split(" ", 1)
        lines.append(f"({int(float(stamp.strip('()'))):d}.000000) {rest}")
    coarse.write_text("\n".join(lines) + "\n")
    first = replay_file(coarse, VMAP, _settings(db_url))
    with engine.connect() as conn:
        stored = archived_in(conn)
    alike = Counter((f.bus, f.ts, f.can_id) for f in stored)
    assert [n for n in alike.values() if n > 1], "the coarse log has frames of one id stamped alike"
    assert first.writer.inserted["raw_frames"] == len(stored) == _archivable(coarse)
    again = replay_file(coarse, VMAP, _settings(db_url))
    assert again.writer.inserted.get("raw_frames", 0) == 0
    with engine.connect() as conn:
        assert archived_in(conn) == stored


def _archivable(log: Path) -> int:
    """How many frames of a log the archive keeps: those an uncollapsed replay archives."""
    from eqgw.ingest.pipeline import IngestPipeline
    from eqgw.ingest.replay import _messages, bindings_for

    bindings, route = bindings_for(parse_vehicle_map(VMAP), _settings("sqlite://"))
    pipeline = IngestPipeline(bindings, channel_map=route)
    pipeline.process_many(_messages(log))
    return pipeline.stats.archived_frames


def test_raw_archive_redecodes_to_the_same_records(db_url: str) -> None:
    """The archive holds every equalizer frame, to the bit (PostgreSQL takes it by binary
    COPY): decoding it again yields the same records."""
    from eqgw.protocol.decode import FrameDecoder
    from eqgw.store.engine import create_engine

    url = db_url
    replay_file(mixed_log.LOG, VMAP, _settings(url))
    engine = create_engine(url)
    with engine.connect() as conn:
        rows = archived_in(conn)
    engine.dispose()
    decoders = {"BUS-101/can0": FrameDecoder((30, 31)), "BUS-102/can1": FrameDecoder((30,))}
    got = []
    for bus, ts, can_id, _, data in rows:
        got += [r.to_dict() for r in decoders[bus].decode(ts, bus, can_id, bytes(data))]
    want = [{**r, "channel": BUS_OF_CHANNEL[r["channel"]]} for r in _expected()]
    # Broadcast requests and commands are archived once, under the bus's first unit.
    assert sorted(json.dumps(r, sort_keys=True) for r in got) == sorted(
        json.dumps(r, sort_keys=True) for r in want
    )


def test_vehicle_map_parsing() -> None:
    assert parse_vehicle_map(["BUS-1"]) == {None: "BUS-1"}
    assert parse_vehicle_map(["can0=A", "can1=B"]) == {"can0": "A", "can1": "B"}
    for bad in ([], ["=A"], ["can0="], ["A", "can0=B"], ["c=A", "c=B"]):
        with pytest.raises(ReplayError):
            parse_vehicle_map(bad)


def test_single_vehicle_for_the_whole_log(tmp_path: Path) -> None:
    url = f"sqlite:///{tmp_path / 'one.db'}"
    summary = replay_file(mixed_log.LOG, ["BUS-9"], Settings(database_url=url))
    # Both channels land on one bus named after the vehicle; only SA 30 is an equalizer.
    assert {(u["bus"], u["sa"]) for u in summary.units} == {("BUS-9", 30)}
    assert summary.unmapped_frames == 0


def test_unmapped_channels_are_counted(tmp_path: Path) -> None:
    url = f"sqlite:///{tmp_path / 'part.db'}"
    summary = replay_file(mixed_log.LOG, ["can0=BUS-101"], _settings(url))
    assert summary.unmapped_frames == sum(
        1 for line in mixed_log.LOG.read_text().splitlines() if " can1 " in line
    )


def test_cli_replay_and_db_upgrade(
    tmp_path: Path, db_url: str, capsys: pytest.CaptureFixture[str]
) -> None:
    cfg = tmp_path / "fleet.toml"
    cfg.write_text(
        '[[vehicles]]\nid = "BUS-101"\nname = "Bus 101"\n[[vehicles]]\nid = "BUS-102"\n'
        '[[buses]]\nname = "BUS-101/can0"\nvehicle_id = "BUS-101"\ninterface = "virtual"\n'
        'channel = "can0"\nequalizer_sas = [30, 31]\n'
    )
    assert main(["db", "upgrade", "--db", db_url]) == 0
    args = ["replay", str(mixed_log.LOG), "--db", db_url, "--config", str(cfg), "-q"]
    args += ["--vehicle", "can0=BUS-101", "--vehicle", "can1=BUS-102"]
    assert main(args) == 0
    out = capsys.readouterr().out
    assert "3893 frames" in out and "640 records" in out
    assert main([*args, "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["records"] == 640
    assert sum(summary["writer"]["inserted"].values()) == 0
    assert main(["replay", str(tmp_path / "missing.log"), "--vehicle", "X", "--db", db_url]) == 1


def test_replay_counts_bad_lines_and_goes_on(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    lines = mixed_log.LOG.read_text().splitlines()
    lines.insert(50, "garbage here with too many values to unpack")
    lines.insert(400, "(nan) can0 18FFD61E#D809B013BA7CC87D R")
    path = tmp_path / "broken.log"
    path.write_text("\n".join(lines) + "\n")
    url = f"sqlite:///{tmp_path / 'bad.db'}"
    summary = replay_file(path, ["can0=BUS-101", "can1=BUS-102"], _settings(url))
    assert summary.records == 640 and summary.read_error is None
    assert summary.bad_lines == 2 and [n for n, _ in summary.bad] == [51, 401]
    assert summary.decode["malformed"] == 4 + 2
    text = summary.text()
    assert "malformed lines: 2 (line 51: not a candump line; line 401: timestamp 'nan'" in text
    assert main(["replay", str(path), "--vehicle", "BUS-9", "--db", url, "-q"]) == 0
    assert "malformed lines: 2" in capsys.readouterr().out


def test_replay_of_a_truncated_log_says_so_and_exits_1(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    import gzip

    packed = gzip.compress(mixed_log.LOG.read_bytes())
    cut = tmp_path / "cut.log.gz"
    cut.write_bytes(packed[: len(packed) // 2])
    url = f"sqlite:///{tmp_path / 'cut.db'}"
    assert main(["replay", str(cut), "--vehicle", "BUS-9", "--db", url, "-q"]) == 1
    out = capsys.readouterr().out
    assert "NOT READ TO THE END: unreadable after " in out and "EOFError" in out


def test_replay_of_a_truncated_blf_says_so_and_exits_1(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    import can

    whole = tmp_path / "whole.blf"
    with can.Logger(str(whole)) as writer:
        for msg in can.LogReader(str(mixed_log.LOG)):
            msg.channel = {"can0": 0, "can1": 1}[msg.channel]
            writer.on_message_received(msg)
    data = whole.read_bytes()
    cut = tmp_path / "cut.blf"
    cut.write_bytes(data[: len(data) // 2])
    url = f"sqlite:///{tmp_path / 'blf.db'}"
    assert main(["replay", str(cut), "--vehicle", "BUS-9", "--db", url, "-q"]) == 1
    out = capsys.readouterr().out
    assert f"truncated: the BLF header says {len(data)} bytes, the file has {len(data) // 2}" in out


def test_other_nodes_global_requests_are_neither_records_nor_archived(tmp_path: Path) -> None:
    base = mixed_log.LOG.read_text()
    # SA 49 asks everyone for PGN 65257, then for DM1: only the second is the equalizers'.
    extra = (
        "(1763700001.000100) can0 18EAFF31#E9FE00 R\n(1763700001.000200) can0 18EAFF31#CAFE00 R\n"
    )
    plain, asked = tmp_path / "plain.log", tmp_path / "asked.log"
    plain.write_text(base)
    asked.write_text(base + extra)
    s_plain = replay_file(plain, VMAP, _settings(f"sqlite:///{tmp_path / 'p.db'}"))
    s_asked = replay_file(asked, VMAP, _settings(f"sqlite:///{tmp_path / 'a.db'}"))
    assert s_asked.records == s_plain.records + 1
    raw = s_asked.writer.inserted["raw_frames"] - s_plain.writer.inserted["raw_frames"]
    assert raw == 1


def test_replay_names_equalizer_like_traffic_it_did_not_decode(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Without --config, a second unit at SA 31 is not silently dropped among other nodes'
    traffic: the summary names its address and the frames, and `--sa 30,31` decodes it."""
    url = f"sqlite:///{tmp_path / 'sa.db'}"
    base = ["replay", str(mixed_log.LOG), "--db", url, "-q", "--vehicle", "can0=BUS-101"]
    base += ["--vehicle", "can1=BUS-102"]
    assert main([*base, "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert {(u["bus"], u["sa"]) for u in summary["units"]} == {
        ("BUS-101/can0", 30),
        ("BUS-102/can1", 30),
    }
    from_31 = summary["decode"]["lookalike"].get("31", 0)
    assert from_31 > 0
    assert main(base) == 0
    assert "SA 31 (" in capsys.readouterr().out
    assert main([*base, "--sa", "30,31", "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert ("BUS-101/can0", 31) in {(u["bus"], u["sa"]) for u in summary["units"]}
    assert "31" not in summary["decode"]["lookalike"]
    # decode names them too
    assert main(["decode", str(mixed_log.LOG)]) == 0
    assert "SA 31 (" in capsys.readouterr().err


def test_frames_to_the_equalizer_never_make_a_unit(db_url: str, tmp_path: Path) -> None:
    """Another vendor's PGN 0xFFD2/0xFFD3 frames (SA 0x33) on a bus with no equalizer: no unit,
    no stored "write", no archived frame; counted. On a bus with a unit, the same frames are
    kept against it, and values outside the manuals' ranges are flagged."""
    foreign = (
        "(1763700000.000000) can0 18FFD233#5555FFFFFFFFFFFF\n"  # control
        "(1763700000.100000) can0 18FFD333#093534FFFFFFFFFF\n"  # OV setpoint 1,333.3 V
        "(1763700000.200000) can0 18FFD333#001200FFFFFFFFFF\n"  # profile 18
    )
    log = tmp_path / "foreign.log"
    log.write_text(foreign)
    summary = replay_file(log, ["BUS-9"], Settings(), database_url=db_url)
    assert summary.units == []
    assert summary.to_no_unit == 3
    assert "never makes a unit" in summary.text()
    engine = create_engine(db_url)
    try:
        counts = _counts(engine)
    finally:
        engine.dispose()
    assert counts.get("units", 0) == 0
    assert counts.get("messages", 0) == 0 and counts.get("raw_frames", 0) == 0

    # With the unit heard first, the writes are its; the absurd values are flagged.
    heard = tmp_path / "heard.log"
    unit = "(1763699999.900000) can0 18FFD41E#0000000000000000\n"
    heard.write_text(unit + foreign)
    summary = replay_file(heard, ["BUS-8"], Settings(), database_url=db_url)
    assert [(u["bus"], u["sa"]) for u in summary.units] == [("BUS-8", 30)]
    assert summary.to_no_unit == 0
    engine = create_engine(db_url)
    try:
        with engine.connect() as conn:
            rows = conn.execute(
                text("SELECT name, fields FROM messages WHERE name = 'parameters' ORDER BY ts")
            ).all()
    finally:
        engine.dispose()
    fields = [r[1] if isinstance(r[1], dict) else json.loads(r[1]) for r in rows]
    assert fields[0]["ov_setpoint_v"] > 1000 and fields[0]["out_of_range"] == ["ov_setpoint_v"]
    assert fields[1]["profile"] == 18 and fields[1]["out_of_range"] == ["profile"]
