"""A database that stops answering without a word (its path blackholed: packets dropped, no
reset), between real processes: `eqgw serve` reaches PostgreSQL through a TCP proxy that
stops forwarding bytes in both directions and keeps every connection open."""

from __future__ import annotations

import re
import sys
import time
from pathlib import Path

import pytest

from tests.cluster_helpers import (
    METRICS_TOKEN,
    operator_key,
    readyz,
    start_simulator,
    write_fleet,
)
from tests.db_helpers import archived_frames
from tests.proc_helpers import Process, eqgw, free_port, wait_until
from tests.proxy_helpers import blackhole_proxy
from tests.support import web
from tests.test_durability import SERVING

NAMES = ["SIM-001", "SIM-002"]


def _newest(url: str) -> dict[str, float]:
    newest: dict[str, float] = {}
    for f in archived_frames(url):
        newest[f.bus] = max(newest.get(f.bus, f.ts), f.ts)
    return newest


def _committed_after(url: str, t: float) -> bool:
    newest = _newest(url)
    return len(newest) == len(NAMES) and all(v > t for v in newest.values())


def _stored(url: str) -> set[tuple[str, int, float]]:
    return {(f.bus, f.can_id, round(f.ts, 3)) for f in archived_frames(url)}


def _records(base: str) -> float:
    """The equalizer records the gateway has decoded (its /metrics)."""
    r = web.get(f"{base}/metrics", headers={"Authorization": f"Bearer {METRICS_TOKEN}"}, timeout=10)
    found = re.search(r"^eqgw_records_total (\S+)$", r.text, re.M)
    return float(found.group(1)) if found else 0.0


def _sent(rec: Path, t0: float, t1: float) -> list[tuple[str, int, float]]:
    import can

    out = []
    for path in sorted(rec.glob("*.log")):
        with can.LogReader(str(path)) as reader:
            out += [
                (path.stem, m.arbitration_id, round(m.timestamp, 3))
                for m in reader
                if t0 <= m.timestamp <= t1
            ]
    return out


@pytest.mark.postgres
@pytest.mark.slow
def test_blackholed_database_503_live_view_and_journal(tmp_path: Path, pg_url: str) -> None:
    """The path to PostgreSQL blackholed: the writer's batch fails at its deadline and its
    rows go to the journal; requests needing the database answer 503 with Retry-After, the
    live view and the fleet list answer from memory; a SIGTERM during the hang journals
    everything held, and the next start writes it (no frame read is lost)."""
    key = operator_key(pg_url, "blackhole")
    rec = tmp_path / "rec"
    sim, sim_port = start_simulator(tmp_path, len(NAMES), "--record", str(rec), "--seed", "3")
    fleet = write_fleet(tmp_path / "fleet.toml", NAMES, sim_port)
    auth = {"Authorization": f"Bearer {key}"}
    with blackhole_proxy(pg_url) as proxy:
        env = {
            "EQGW_DATABASE_URL": proxy.url(pg_url),
            "EQGW_CLUSTER_MODE": "off",
            "EQGW_API_METRICS_TOKEN": METRICS_TOKEN,
        }

        def start() -> tuple[Process, str]:
            port = free_port()
            gw = Process(
                eqgw("serve", "--config", str(fleet)), tmp_path, {**env, "EQGW_API_PORT": str(port)}
            )
            gw.wait_line(SERVING, timeout=120)
            return gw, f"http://127.0.0.1:{port}"

        gw, base = start()
        try:
            began = time.time()
            wait_until(lambda: _committed_after(pg_url, began), 60, "every bus committed")
            api = f"{base}/api/v1"
            assert web.get(f"{api}/vehicles", headers=auth, timeout=10).status_code == 200
            records_before = _records(base)
            fault = proxy.blackhole()

            # Past the key cache (5 s): the key is looked up again, the database does not
            # answer, the last answer stands. Each request answers within its client timeout.
            for _ in range(3):
                live = web.get(f"{api}/vehicles/SIM-001/live", headers=auth, timeout=8)
                assert live.status_code == 200, live.text
                assert live.json()["units"], live.json()
                listing = web.get(f"{api}/vehicles", headers=auth, timeout=8)
                assert listing.status_code == 200, listing.text
                assert {v["id"] for v in listing.json()["vehicles"]} == set(NAMES)
                needs_db = web.get(f"{api}/vehicles/SIM-001/faults", headers=auth, timeout=8)
                assert needs_db.status_code == 503, needs_db.text
                assert needs_db.headers.get("Retry-After"), needs_db.headers
                time.sleep(1.0)
            command = web.post(
                f"{api}/vehicles/SIM-001/commands",
                json={"can_onoff_enable": True},
                headers=auth,
                timeout=8,
            )
            assert command.status_code == 503, command.text
            assert command.headers.get("Retry-After"), command.headers

            # The hung batch failed at its deadline: its rows and what followed are journaled.
            def journaled() -> bool:
                body = readyz(base)
                return body is not None and body["database"]["writer"]["journal_rows"] > 0

            wait_until(journaled, 40, "rows journaled during the hang")
            journal_at = time.time()

            # The hang covers enough equalizer messages for "none lost" to say something
            # (however soon /readyz reported the journal).
            wait_until(lambda: _records(base) >= records_before + 30, 30,
                       "30 equalizer records read during the hang")  # fmt: skip
            term = time.time()
            gw.stop()
            first_run = gw.output()
            assert "kept in the journal" in first_run, first_run[-3000:]

            proxy.restore()
            gw, base = start()
            later = time.time() + 1
            wait_until(lambda: _committed_after(pg_url, later), 90, "ingest after the restart")
            assert "rows left unwritten by the previous run" in gw.output(), gw.output()[-3000:]
        except BaseException:
            sys.stderr.write(f"--- the gateway's output\n{gw.output()[-6000:]}\n")
            raise
        finally:
            gw.stop()
            sim.stop()
    stored = _stored(pg_url)
    kept_ids = {(b, c) for b, c, _ in stored}
    sent = [f for f in _sent(rec, began, term - 0.5) if (f[0], f[1]) in kept_ids]
    missing = [f for f in sent if f not in stored]
    during = [f for f in sent if f[2] >= fault]
    sys.stderr.write(
        f"blackhole: journaled {journal_at - fault:.1f} s after the fault; "
        f"{len(missing)} of {len(sent)} frames lost ({len(during)} sent during the hang)\n"
    )
    assert len(during) > 20
    assert not missing, missing[:5]


@pytest.mark.postgres
def test_a_stop_while_a_write_hangs_journals_the_batch_in_flight(
    tmp_path: Path, pg_url: str
) -> None:
    """The writer's thread stuck in a write the database never answers: a stop does not wait
    for it; the batch in flight and what queued behind it go to the journal (should the write
    still commit, the journal's copy adds nothing: natural keys)."""
    from eqgw.config import WriterSettings
    from eqgw.ingest.journal import RowJournal
    from eqgw.ingest.rows import MeasurementRow
    from eqgw.ingest.writer import BatchedWriter
    from eqgw.store.engine import create_engine
    from eqgw.store.migrate import upgrade_engine
    from tests.test_durability import _unit_rows

    setup = create_engine(pg_url)
    upgrade_engine(setup)
    setup.dispose()
    with blackhole_proxy(pg_url) as proxy:
        url = proxy.url(pg_url)
        engine = create_engine(url)
        journal = RowJournal.open(tmp_path, url)
        writer = BatchedWriter(
            engine, WriterSettings(flush_ms=20, write_timeout_s=120), journal=journal
        )
        writer.start()
        writer.put(_unit_rows(3))
        assert writer.flush(30)
        proxy.blackhole()
        writer.put(_unit_rows(5, t0=2000.0))
        wait_until(lambda: writer.status().state == "writing" and writer.pending, 10, "a write")
        writer.put(_unit_rows(2, t0=3000.0))  # queued behind the hung batch
        assert writer.stop(1.0) == 0
        assert journal.rows == 7 + 4
        kept = []
        while (entry := journal.first()) is not None:
            kept += [r.values["ts"] for r in entry[1] if isinstance(r, MeasurementRow)]
            journal.ack(entry[0])
        assert sorted(kept) == [2000.0, 2001.0, 2002.0, 2003.0, 2004.0, 3000.0, 3001.0]
        engine.dispose()
