"""A unit is its NAME where claims are seen (SQLite and PostgreSQL): two nodes of an
independent J1939 stack (can-j1939) contend for the equalizer's address 30 on a virtual bus;
their frames, with an equalizer that identified itself before, are stored. The unit row takes
the winning NAME and drops the old node's identity at once, the owner change is a period of
its own, and a log replayed again or out of order changes nothing of that."""

from __future__ import annotations

import time
import uuid
from collections.abc import Iterator
from pathlib import Path

import can
import j1939
import pytest
from sqlalchemy import text

from eqgw.config import Settings
from eqgw.ingest.replay import replay_file
from eqgw.store import queries
from eqgw.store.engine import create_engine
from eqgw.store.migrate import upgrade_engine
from tests.fixtures import mixed_log
from tests.j1939_helpers import Observer, stack_name

BUS = "BUS-101"
VEHICLE = "BUS-101"


def _contention() -> tuple[list[can.Message], int, int]:
    """The Address Claimed frames two can-j1939 nodes put on a bus: the first claims 30,
    then one with a lower NAME takes it. Returns the frames and both NAMEs."""
    old, new = stack_name(1, 130, 7), stack_name(0, 0, 3)
    assert new.value < old.value
    channel = f"j1939-name-{uuid.uuid4().hex}"
    observer = Observer(channel)
    ecus: list[j1939.ElectronicControlUnit] = []
    try:
        for name in (old, new):
            ecu = j1939.ElectronicControlUnit()
            ecu.connect(interface="virtual", channel=channel)
            ecus.append(ecu)
            ca = j1939.ControllerApplication(name, 30)
            ecu.add_ca(controller_application=ca)
            ca.start()
            deadline = time.monotonic() + 10
            while ca.state != j1939.ControllerApplication.State.NORMAL:
                assert time.monotonic() < deadline, "can-j1939 did not claim"
                time.sleep(0.05)
        claims = observer.frames(pf=0xEE)
    finally:
        for ecu in ecus:
            ecu.disconnect()
            ecu.stop()
        observer.bus.shutdown()
    names = [int.from_bytes(m.data, "little") for m in claims]
    assert names[0] == old.value and new.value in names
    return claims, old.value, new.value


def _log() -> list[can.Message]:
    frames = [m for m in can.LogReader(str(mixed_log.LOG)) if m.channel == "can0"]
    return frames


def _timed(claims: list[can.Message], start: float) -> list[can.Message]:
    out = []
    for i, m in enumerate(claims):
        out.append(
            can.Message(
                timestamp=start + 0.01 * i,
                arbitration_id=m.arbitration_id,
                data=bytes(m.data),
                channel="can0",
            )
        )
    return out


@pytest.fixture(scope="module")
def contention() -> tuple[list[can.Message], int, int]:
    return _contention()


@pytest.fixture
def url(db_url: str) -> Iterator[str]:
    engine = create_engine(db_url)
    upgrade_engine(engine)
    engine.dispose()
    yield db_url


def _replay(url: str, frames: list[can.Message], tmp_path: Path) -> None:
    replay_file(
        tmp_path / "frames.log",
        {None: VEHICLE},
        Settings(database_url=url),
        messages=frames,
        migrate=False,
    )


def _unit(url: str) -> dict[str, object]:
    engine = create_engine(url)
    try:
        with engine.connect() as conn:
            uid = queries.unit_id_of(conn, BUS, 30)
            assert uid is not None
            row = queries.get_unit(conn, uid)
            assert row is not None
            return {**row, "owners": queries.unit_owners(conn, uid)}
    finally:
        engine.dispose()


def test_the_unit_takes_the_new_nodes_name_and_drops_the_old_identity(
    url: str, tmp_path: Path, contention: tuple[list[can.Message], int, int]
) -> None:
    claims, old, new = contention
    log = _log()
    first, last = log[0].timestamp, log[-1].timestamp
    # The old node claims 30 before the log (it is the equalizer that identifies itself in
    # it), the contention comes after the log's last frame.
    before = _timed(claims[:1], first - 1.0)
    after = _timed(claims[1:], last + 1.0)
    _replay(url, [*before, *log], tmp_path)
    unit = _unit(url)
    assert unit["name"] == f"0x{old:016X}"
    assert unit["model"] is not None and unit["series"] is not None  # identified in the log
    assert unit["owners"] == [{"name": f"0x{old:016X}", "from": first - 1.0, "to": None}]

    _replay(url, after, tmp_path)
    unit = _unit(url)
    changed_at = next(m.timestamp for m in after if int.from_bytes(m.data, "little") == new)
    assert unit["name"] == f"0x{new:016X}"
    # Nothing of the old node is shown for the new one.
    assert (unit["model"], unit["series"], unit["software_id"]) == (None, None, None)
    assert unit["owners"] == [
        {"name": f"0x{old:016X}", "from": first - 1.0, "to": changed_at},
        {"name": f"0x{new:016X}", "from": changed_at, "to": None},
    ]

    # The whole log again, out of order (the old node's identification is older than the new
    # owner): nothing changes.
    _replay(url, [*before, *log, *after], tmp_path)
    assert _unit(url) == unit
    engine = create_engine(url)
    try:
        with engine.connect() as conn:
            claim_rows = conn.execute(
                text("SELECT count(*) FROM messages WHERE name = 'address_claim'")
            ).scalar()
            owners = conn.execute(text("SELECT count(*) FROM unit_owners")).scalar()
            uid = queries.unit_id_of(conn, BUS, 30)
            assert uid is not None
            # A history read of a range inside the old node's period names only it.
            assert queries.unit_owners(conn, uid, first, last) == [unit["owners"][0]]  # type: ignore[index]
    finally:
        engine.dispose()
    assert owners == 2 and claim_rows == 2


def test_the_migration_fills_names_from_the_stored_claims(empty_db_url: str) -> None:
    """A database of 0011 with address claims stored: 0015 gives each unit its latest NAME
    and a period per NAME; units never claimed keep NULL, and every row stays."""
    engine = create_engine(empty_db_url)
    try:
        upgrade_engine(engine, "0011_seclogin")
        claims = [
            (10.0, "0x00000000000000A0", False),
            (20.0, "0x00000000000000A0", False),  # a restart: the same node
            (30.0, "0x0000000000000010", True),
        ]
        with engine.begin() as conn:
            conn.execute(text("INSERT INTO vehicles (id, name) VALUES ('V1', 'V1')"))
            for sa in (30, 31):
                conn.execute(
                    text(
                        "INSERT INTO units (bus, sa, vehicle_id, model) "
                        "VALUES ('V1/can0', :sa, 'V1', 'EQ8001')"
                    ),
                    {"sa": sa},
                )
            uid = conn.execute(text("SELECT id FROM units WHERE sa = 30")).scalar_one()
            for ts, name, changed in claims:
                fields = (
                    f'{{"name": "{name}", "previous_name": null, '
                    f'"owner_changed": {"true" if changed else "false"}}}'
                )
                cast = "CAST(:f AS JSONB)" if engine.dialect.name == "postgresql" else ":f"
                conn.execute(
                    text(
                        "INSERT INTO messages (unit_id, ts, name, idx, fields) "
                        f"VALUES (:u, :ts, 'address_claim', 0, {cast})"
                    ),
                    {"u": uid, "ts": ts, "f": fields},
                )
        upgrade_engine(engine)
        with engine.connect() as conn:
            names = dict(conn.execute(text("SELECT sa, name FROM units")).all())
            assert names == {30: "0x0000000000000010", 31: None}
            assert queries.unit_owners(conn, uid) == [
                {"name": "0x00000000000000A0", "from": 10.0, "to": 30.0},
                {"name": "0x0000000000000010", "from": 30.0, "to": None},
            ]
            models = conn.execute(text("SELECT model FROM units ORDER BY sa")).scalars().all()
            assert models == ["EQ8001", "EQ8001"]  # identity is the writer's to clear
    finally:
        engine.dispose()
