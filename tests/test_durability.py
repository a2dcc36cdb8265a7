"""Nothing accepted is lost: `eqgw serve` (cluster mode auto, the default on PostgreSQL) through a
PostgreSQL outage, a SIGTERM or a SIGKILL in the middle of it, and its writer's own failures.

Each process test runs a private PostgreSQL cluster (stopped and started under the gateway) and
`eqgw simulate --record`, whose log of every frame it sent is compared with the raw archive.
"""

from __future__ import annotations

import asyncio
import re
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import can
import httpx
import pytest
from sqlalchemy import text

from eqgw.config import WriterSettings
from eqgw.ingest.journal import RowJournal
from eqgw.ingest.rows import EpisodeRow, MeasurementRow, Row, UnitRow, VehicleRow
from eqgw.ingest.writer import BatchedWriter
from eqgw.store.engine import create_engine
from eqgw.store.migrate import upgrade_engine
from eqgw.store.writes import EpisodeValues
from tests.cluster_helpers import LISTENING, METRICS_TOKEN, readyz, write_fleet
from tests.db_helpers import archived_frames
from tests.proc_helpers import Process, eqgw, free_port, wait_until
from tests.test_ingest_outage import ThrowawayCluster, throwaway_pg

__all__ = ["throwaway_pg"]  # the fixture, used by name below

SERVING = re.compile(r"serving on (\S+)")
Window = tuple[float, float]


class Rig:
    """A recording simulator, a fleet file and `eqgw serve` on a private PostgreSQL."""

    def __init__(self, tmp_path: Path, pg: ThrowawayCluster, vehicles: int = 4) -> None:
        self.tmp = tmp_path
        self.pg = pg
        self.names = [f"SIM-{i:03d}" for i in range(1, vehicles + 1)]
        self.rec = tmp_path / "rec"
        self.sim = Process(
            eqgw(
                "simulate",
                "--vehicles",
                str(vehicles),
                "--listen",
                "127.0.0.1:0",
                "--record",
                str(self.rec),
                "--seed",
                "7",
            ),
            tmp_path,
        )
        port = int(self.sim.wait_line(LISTENING).group(2))
        self.fleet = write_fleet(tmp_path / "fleet.toml", self.names, port)
        self.gw: Process | None = None
        self.base = ""

    def start_gateway(self, **env: str) -> None:
        port = free_port()
        self.base = f"http://127.0.0.1:{port}"
        self.gw = Process(
            eqgw("serve", "--config", str(self.fleet)),
            self.tmp,
            {
                "EQGW_DATABASE_URL": self.pg.url,
                "EQGW_API_PORT": str(port),
                "EQGW_API_METRICS_TOKEN": METRICS_TOKEN,
                **env,
            },
        )
        self.gw.wait_line(SERVING, timeout=120)

    def committed_after(self, t: float) -> bool:
        """Whether every bus has a raw frame newer than `t` in the database."""
        try:
            newest = _newest(self.pg.url)
        except Exception:
            return False
        return len(newest) == len(self.names) and all(v > t for v in newest.values())

    def close(self) -> None:
        if self.gw is not None and self.gw.proc.poll() is None:
            self.gw.stop()
        self.sim.stop()


@pytest.fixture
def rig(tmp_path: Path, throwaway_pg: ThrowawayCluster) -> Iterator[Rig]:
    r = Rig(tmp_path, throwaway_pg)
    try:
        yield r
    finally:
        r.close()


def _newest(url: str) -> dict[str, float]:
    newest: dict[str, float] = {}
    for f in archived_frames(url):
        newest[f.bus] = max(newest.get(f.bus, f.ts), f.ts)
    return newest


def _stored(url: str) -> set[tuple[str, int, float]]:
    return {(f.bus, f.can_id, round(f.ts, 3)) for f in archived_frames(url)}


def _sent(rec: Path) -> list[tuple[str, int, float]]:
    out = []
    for path in sorted(rec.glob("*.log")):
        with can.LogReader(str(path)) as reader:
            out += [(path.stem, m.arbitration_id, round(m.timestamp, 3)) for m in reader]
    return out


def lost_frames(
    rig: Rig, windows: list[Window], limit: int | None = 5
) -> tuple[int, int, list[Any]]:
    """(frames sent within `windows` that the raw archive lacks, frames sent within them,
    the first `limit` of the missing). Only identifiers the archive keeps at all count."""
    stored = _stored(rig.pg.url)
    kept_ids = {(b, c) for b, c, _ in stored}
    sent = [
        f
        for f in _sent(rig.rec)
        if (f[0], f[1]) in kept_ids and any(a <= f[2] <= b for a, b in windows)
    ]
    missing = [f for f in sent if f not in stored]
    return len(missing), len(sent), missing[:limit]


def _sent_since(rec: Path, t: float) -> int:
    """Frames the simulator recorded after `t` so far (a line it is writing is skipped)."""
    n = 0
    for path in rec.glob("*.log"):
        for line in path.read_text().splitlines():
            try:
                n += float(line[1 : line.index(")")]) > t
            except ValueError:
                continue
    return n


def _journal_rows(rig: Rig) -> int:
    body = readyz(rig.base)
    return int(body["database"]["writer"]["journal_rows"]) if body else 0


def _outage(rig: Rig, until: Any, what: str) -> tuple[float, float]:
    """PostgreSQL stopped until `until()` holds (the state the test needs is reached)."""
    t0 = time.time()
    rig.pg.stop()
    wait_until(until, 90, what)
    rig.pg.start()
    return t0, time.time()


@pytest.mark.postgres
@pytest.mark.slow
def test_outage_in_cluster_mode_loses_nothing(rig: Rig) -> None:
    """A lease round fails during the outage (the gateway fences): it stops command delivery
    but goes on reading, and commits everything read once the database is back."""
    rig.start_gateway()
    start = time.time()
    wait_until(lambda: rig.committed_after(start), 90, "every bus committed")
    outage_began = time.time()

    def fenced_with_frames_sent() -> bool:
        body = readyz(rig.base)
        fenced = body is not None and body["cluster"]["fenced"] >= 1
        return fenced and _sent_since(rig.rec, outage_began) > 40

    down, up = _outage(rig, fenced_with_frames_sent, "a fence and frames sent meanwhile")
    wait_until(lambda: rig.committed_after(up + 2), 90, "ingest resumed after the outage")
    body = readyz(rig.base)
    assert body is not None and body["cluster"]["fenced"] >= 1, body
    end = time.time()
    assert rig.gw is not None
    rig.gw.stop()
    rig.sim.stop()
    lost, sent, some = lost_frames(rig, [(start, end - 1.0)])
    sys.stderr.write(f"outage {up - down:.1f} s: {lost} of {sent} frames lost\n")
    assert lost_frames(rig, [(down, up)])[1] > 20  # frames were sent during the outage
    assert lost == 0, some


@pytest.mark.postgres
@pytest.mark.slow
def test_sigterm_during_outage_keeps_what_was_held(rig: Rig) -> None:
    """Stopped (SIGTERM) while PostgreSQL is down: the rows held go to the journal and are
    written by the next start; only frames sent while no gateway ran are missing."""
    rig.start_gateway()
    start = time.time()
    wait_until(lambda: rig.committed_after(start), 90, "every bus committed")
    rig.pg.stop()
    outage_began = time.time()
    wait_until(
        lambda: _journal_rows(rig) > 0 and _sent_since(rig.rec, outage_began) > 60,
        90,
        "part of what is held spilled to the journal",
    )
    assert rig.gw is not None
    term = time.time()
    rig.gw.stop()
    first_run = rig.gw.output()
    rig.pg.start()
    restart = time.time()
    rig.start_gateway()
    # The second window starts 15 s after the restart (the restarted gateway reads from its
    # start, which a loaded machine makes slow). Until frames stamped 10 s into it are
    # stored: the window then holds that much traffic however slowly the gateway restarted.
    second_window = restart + 15.0
    later = max(time.time() + 1, second_window + 10.0)
    wait_until(lambda: rig.committed_after(later), 90, "ingest after the restart")
    second_run = rig.gw.output()
    end = time.time()
    rig.gw.stop()
    rig.sim.stop()
    # Frames stamped up to the SIGTERM were read, but for those still on their way: the
    # simulator stamps a frame with its scheduled time and sends it at its next tick, and on a
    # loaded machine (load 13-20 seen) both it and the reader fall a burst or so behind.
    windows = [(start, term - 2.0), (second_window, end - 2.0)]
    lost, sent, some = lost_frames(rig, windows)
    sys.stderr.write(f"SIGTERM during an outage: {lost} of {sent} frames lost\n")
    assert sent > 40
    # Where a lost frame lies says what lost it: at the outage's start (a batch in flight),
    # or right before the SIGTERM (frames still on their way to the reader).
    when = {"start": start, "outage": outage_began, "term": term, "restart": restart}
    assert lost == 0, (some, when)
    assert "kept in the journal" in first_run, first_run[-3000:]
    assert "rows left unwritten by the previous run" in second_run, second_run[-3000:]


@pytest.mark.postgres
@pytest.mark.slow
def test_sigkill_during_outage_loses_at_most_the_last_flush(rig: Rig) -> None:
    """Killed (SIGKILL) while PostgreSQL is down: everything but the last flush interval was
    in the journal, and the next start writes it."""
    rig.start_gateway()
    start = time.time()
    wait_until(lambda: rig.committed_after(start), 90, "every bus committed")
    rig.pg.stop()
    # Past two spills: what is read during the outage has been going to the journal a while.
    outage_began = time.time()
    first = wait_until(lambda: _journal_rows(rig), 90, "a first spill to the journal")
    wait_until(
        lambda: _journal_rows(rig) > first and _sent_since(rig.rec, outage_began) > 60,
        90,
        "a later spill to the journal",
    )
    assert rig.gw is not None
    killed = time.time()
    rig.gw.kill()
    rig.pg.start()
    rig.start_gateway()
    later = time.time() + 1
    wait_until(lambda: rig.committed_after(later), 90, "ingest after the restart")
    rig.gw.stop()
    rig.sim.stop()
    newest_before = max(
        f[2] for f in _stored(rig.pg.url) if f[2] <= killed
    )  # the last frame kept from before the kill
    sys.stderr.write(f"SIGKILL in an outage: the last {killed - newest_before:.2f} s lost\n")
    # The flush interval (0.5 s) plus the reader's hand-over (0.1 s), with room for a busy
    # machine; without the journal everything since the outage began (8 s) is lost.
    lost, sent, some = lost_frames(rig, [(start, killed - 1.5)])
    assert sent > 40
    assert lost == 0, some


# -- the writer thread's own failures -----------------------------------------------------


def _m(ts: float) -> MeasurementRow:
    return MeasurementRow(
        ("V1/can0", 30), {"ts": ts, "v12": 12.6, "v24": 25.2, "i12": 1.0, "i24": 2.0}
    )


def _unit_rows(n: int, t0: float = 1000.0) -> list[Row]:
    return [
        _vehicle("V1"),
        UnitRow(("V1/can0", 30), "V1"),
        *[_m(t0 + i) for i in range(n)],
    ]


def _vehicle(vehicle_id: str) -> VehicleRow:
    return VehicleRow(vehicle_id, {"id": vehicle_id, "name": vehicle_id, "depot": None})


def _measurements(engine: Any) -> int:
    with engine.connect() as conn:
        return int(conn.execute(text("SELECT count(*) FROM measurements")).scalar_one())


def test_a_row_the_writer_cannot_build_is_dropped_not_fatal(
    engine: Any, caplog: pytest.LogCaptureFixture
) -> None:
    """A row of an unknown kind used to end the writer thread silently (nothing written
    after it, readiness still true); it is now dropped, logged and counted."""
    writer = BatchedWriter(engine, WriterSettings(flush_ms=20))
    writer.start()
    try:
        not_a_row: Any = ("no such kind", "x", {})
        writer.put([not_a_row, *_unit_rows(5)])
        assert writer.flush(20)
        writer.put([_m(2000.0)])
        assert writer.flush(20)
        st = writer.status()
        assert st.rejected_rows == 1
        assert st.state != "dead"
    finally:
        assert writer.stop(10) == 0
    assert _measurements(engine) == 6
    assert "dropped a row" in caplog.text


async def test_writer_error_turns_readiness_false_and_the_writer_restarts(
    db_url: str, caplog: pytest.LogCaptureFixture, monkeypatch: pytest.MonkeyPatch
) -> None:
    """An unexpected error while writing (not a database error) used to end the writer
    thread: last_error None, /readyz 200, nothing written from then on. Now it is logged,
    /readyz is a 503 while it lasts, and the writer's loop starts again with its rows."""
    import threading

    import eqgw.ingest.writer as writer_mod
    from tests.api_helpers import served, wait_for

    real = writer_mod.write_batch
    broken = threading.Event()

    def faulty(*args: Any, **kwargs: Any) -> Any:
        if broken.is_set():
            raise RuntimeError("a bug in the writer")
        return real(*args, **kwargs)

    monkeypatch.setattr(writer_mod, "write_batch", faulty)
    async with served(db_url, vehicles=1) as s:
        writer = s.rt.ingest.writer
        assert (await s.client.get("/readyz")).status_code == 200
        broken.set()

        async def not_ready() -> httpx.Response | None:
            r = await s.client.get("/readyz", headers=s.auth())  # the details need a key
            return r if r.status_code == 503 else None

        r = await wait_for(not_ready, 30, "/readyz to turn 503")
        assert "a bug in the writer" in r.json()["database"]["error"]
        committed = writer.status().committed_rows
        broken.clear()
        await wait_for(
            lambda: asyncio.sleep(0, writer.status().committed_rows > committed), 30, "writes"
        )
        assert (await s.client.get("/readyz")).status_code == 200
        assert writer.status().state != "dead"
    assert "database writer failed" in caplog.text


def test_journal_rows_survive_a_new_writer_and_go_first(db_url: str, tmp_path: Path) -> None:
    """Rows spilled by one writer (its database away) are written by the next writer on the
    same journal before its own rows (episodes: the later state must win)."""
    engine = create_engine(db_url)
    upgrade_engine(engine)
    journal = RowJournal.open(tmp_path, db_url)
    journal.append(_unit_rows(4))
    journal.close()
    assert (tmp_path / journal.path.name).exists()
    journal = RowJournal.open(tmp_path, db_url)
    assert journal.inherited_rows == 6
    writer = BatchedWriter(engine, WriterSettings(flush_ms=20), journal=journal)
    writer.start()
    try:
        assert writer.wait_replayed(30)
        writer.put([_m(5000.0)])
        assert writer.flush(30)
        st = writer.status()
        assert st.replayed_rows == 6 and st.journal_rows == 0 and st.committed_rows == 1
    finally:
        assert writer.stop(10) == 0
    assert _measurements(engine) == 5
    assert not journal.path.exists()  # an empty journal is removed
    engine.dispose()


def test_a_second_process_takes_the_next_journal_slot(tmp_path: Path, db_url: str) -> None:
    """Two gateways of one database in one folder never share a journal file."""
    a = RowJournal.open(tmp_path, db_url)
    b = RowJournal.open(tmp_path, db_url)
    try:
        assert a.path != b.path
        a.append([_vehicle("V")])
    finally:
        b.close()
    a_path = a.path
    a.close(remove=False)  # a killed process leaves its file (and its lock goes with it)
    c = RowJournal.open(tmp_path, db_url)
    try:
        assert c.path == a_path and c.inherited_rows == 1
    finally:
        c.close(remove=True)


def test_a_journal_nobody_holds_is_adopted(tmp_path: Path, db_url: str) -> None:
    """A second gateway's journal left behind (it was killed, and only one gateway runs now)
    is moved into the journal of the next gateway that starts, then removed."""
    a = RowJournal.open(tmp_path, db_url)
    b = RowJournal.open(tmp_path, db_url)
    b.append([_vehicle("V"), _vehicle("W")])
    b_path = b.path
    b.close(remove=False)
    a.close()  # empty: removed
    c = RowJournal.open(tmp_path, db_url)
    try:
        assert c.path == a.path and c.inherited_rows == 2
        assert not b_path.exists()
        entry = c.first()
        assert entry is not None and entry[1] == [_vehicle("V"), _vehicle("W")]
    finally:
        c.close(remove=True)


# -- serving on ---------------------------------------------------------------------------

# Loaded into the child by a sitecustomize: at the moment `serving on` is written, connect to
# the port from inside the process (the kernel answers for a listening socket whatever the
# event loop is doing) and say whether it accepted.
_HOOK = """
import os, socket, sys

class _Out:
    def __init__(self, out):
        self._out = out
    def write(self, s):
        if "serving on" in s:
            try:
                socket.create_connection(("127.0.0.1", int(os.environ["EQGW_API_PORT"])), 2).close()
                self._out.write("test-hook: accepts\\n")
            except OSError as exc:
                self._out.write(f"test-hook: refused ({exc})\\n")
        return self._out.write(s)
    def __getattr__(self, name):
        return getattr(self._out, name)

sys.stdout = _Out(sys.stdout)
"""


def test_serving_on_is_printed_once_the_port_accepts(tmp_path: Path) -> None:
    """`serving on` used to be printed before uvicorn listened: a client that connected on
    seeing it could be refused (the port is bound early, listened on late)."""
    from tests.proc_helpers import ROOT

    hook = tmp_path / "hook"
    hook.mkdir()
    (hook / "sitecustomize.py").write_text(_HOOK)
    port = free_port()
    proc = Process(
        eqgw("serve"),
        tmp_path,
        {
            "EQGW_DATABASE_URL": f"sqlite:///{tmp_path / 'db.sqlite'}",
            "EQGW_API_PORT": str(port),
            "PYTHONPATH": f"{hook}:{ROOT}",
        },
    )
    try:
        proc.wait_line(SERVING, timeout=120)
        verdict = proc.wait_line(re.compile(r"test-hook: (\w+)"), timeout=10)
        assert verdict.group(1) == "accepts", proc.output()[-2000:]
    finally:
        proc.stop()


def test_journal_replay_order_keeps_the_later_episode_state(db_url: str, tmp_path: Path) -> None:
    """An episode spilled open and later closed in memory ends closed in the database."""
    engine = create_engine(db_url)
    upgrade_engine(engine)
    key = (("V1/can0", 30), "OVF", 1000.0)
    row: EpisodeValues = {
        "fault": "OVF",
        "started_at": 1000.0,
        "last_seen_at": 1000.0,
        "source": "dm1",
        "state": "active",
        "ended_at": None,
        "ended_by": None,
        "occurrence_count": 1,
        "spn": 168,
        "fmi": 0,
    }
    journal = RowJournal.open(tmp_path, db_url)
    journal.append([*_unit_rows(0), EpisodeRow(key, row)])
    journal.close()
    journal = RowJournal.open(tmp_path, db_url)
    writer = BatchedWriter(engine, WriterSettings(flush_ms=20), journal=journal)
    closed: EpisodeValues = {**row, "state": "closed", "ended_at": 1001.0, "ended_by": "dm1"}
    writer.put([EpisodeRow(key, closed)])  # accepted before the thread starts
    writer.start()
    try:
        assert writer.flush(30)
    finally:
        assert writer.stop(10) == 0
    with engine.connect() as conn:
        state = conn.execute(text("SELECT state FROM fault_episodes")).scalar_one()
    assert state == "closed"
    engine.dispose()
