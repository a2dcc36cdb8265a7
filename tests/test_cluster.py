"""Several `eqgw serve` on one PostgreSQL: exclusive bus leases, takeover after SIGKILL with
nothing committed lost, commands delivered by the bus owner whichever gateway took them, and
websockets on any gateway seeing every bus."""

from __future__ import annotations

import json
import os
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from sqlalchemy import text
from websockets.sync.client import connect as ws_connect

from eqgw.cluster.fanout import PAYLOAD_LIMIT, decode_batch, encode_batches
from eqgw.cluster.leases import APP_PREFIX, NAMEDATALEN, namespace_of
from eqgw.cluster.settings import ClusterSettings
from eqgw.ingest.events import LIVE, Event, UnitRef
from eqgw.ingest.rows import MeasurementRow, UnitRow, VehicleRow
from eqgw.store.engine import create_engine
from tests.cluster_helpers import (
    operator_key,
    readyz,
    start_gateway,
    start_simulator,
    write_fleet,
)
from tests.db_helpers import query
from tests.proc_helpers import ROOT, Process, wait_until
from tests.proxy_helpers import BlackholeProxy
from tests.support import web

BUSES = [f"SIM-00{i}" for i in range(1, 5)]


def test_fanout_batches_stay_under_the_notify_limit() -> None:
    evs = [
        Event(
            LIVE, UnitRef(f"V{i}", f"V{i}/can0", 30), 1.5 + i, {"slot": "voltages", "x": "y" * 50}
        )
        for i in range(500)
    ]
    huge = Event(LIVE, UnitRef("V", "V/can0", 30), 1.0, {"slot": "dm1", "x": "z" * 9000})
    payloads = encode_batches("gw-a", [*evs[:250], huge, *evs[250:]])
    assert len(payloads) > 1
    assert all(len(p.encode()) <= PAYLOAD_LIMIT for p in payloads)
    got = [ev for p in payloads for ev in decode_batch(p)[1]]
    assert [(e.kind, e.unit, e.ts, e.data) for e in got] == [
        (e.kind, e.unit, e.ts, e.data) for e in evs
    ]
    assert all(e.origin == "gw-a" for e in got)


def _cluster(base: str) -> dict[str, Any] | None:
    body = readyz(base)
    return None if body is None else body.get("cluster")


def _owned(base: str) -> set[str]:
    c = _cluster(base)
    return set(c["owned"]) if c else set()


class _WsWatch:
    """A websocket client on a thread, recording (type, vehicle, wall time) of every event."""

    def __init__(self, url: str) -> None:
        self.url = url
        self.events: list[tuple[str, str, float, dict[str, Any]]] = []
        self.error: Exception | None = None
        self._stop = threading.Event()
        self._open = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()
        assert self._open.wait(15), f"websocket did not open: {self.error!r}"

    def _run(self) -> None:
        try:
            with ws_connect(self.url, open_timeout=10) as conn:
                self._open.set()
                while not self._stop.is_set():
                    try:
                        raw = conn.recv(timeout=0.5)
                    except TimeoutError:
                        continue
                    msg = json.loads(raw)
                    self.events.append((msg["type"], msg.get("vehicle_id", ""), time.time(), msg))
        except Exception as exc:
            self.error = exc

    def seen(self, kind: str, vehicle: str, after: float = 0.0) -> bool:
        assert self.error is None, f"websocket client failed: {self.error!r}"
        return any(k == kind and v == vehicle and t > after for k, v, t, _ in self.events)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=10)


def _diagnose(gw: dict[str, tuple[Process, str]], pg_url: str) -> None:
    """What the gateways say, written out when a check fails (pytest shows it)."""
    now = time.time()
    ages = {bus: (n, round(now - ts, 1)) for bus, (n, ts) in _committed(pg_url).items()}
    sys.stderr.write(f"committed (rows, age of newest s): {ages}\n")
    for name, (proc, base) in gw.items():
        sys.stderr.write(f"--- {name}: readyz {readyz(base)}\n{proc.output()[-4000:]}\n")


@pytest.fixture
def fleet(tmp_path: Path, pg_url: str) -> Iterator[tuple[Path, str, str]]:
    """A migrated schema with an operator key, and a 4-vehicle simulator over socketcand."""
    key = operator_key(pg_url, "cluster test")
    sim, port = start_simulator(tmp_path, len(BUSES))
    try:
        yield write_fleet(tmp_path / "fleet.toml", BUSES, port), key, pg_url
    finally:
        sim.stop()


def _committed(pg_url: str) -> dict[str, tuple[int, float]]:
    """Per bus: measurement rows and the newest of their timestamps, as committed."""
    rows = query(
        pg_url,
        "SELECT u.bus, count(*), max(m.ts) FROM measurements m "
        "JOIN units u ON u.id = m.unit_id GROUP BY u.bus",
    )
    return {r[0]: (int(r[1]), float(r[2])) for r in rows}


def _rows_up_to(pg_url: str, bus: str, ts: float) -> int:
    rows = query(
        pg_url,
        "SELECT count(*) FROM measurements m JOIN units u ON u.id = m.unit_id "
        "WHERE u.bus = :bus AND m.ts <= :ts",
        bus=bus,
        ts=ts,
    )
    return int(rows[0][0])


@pytest.mark.postgres
def test_two_gateways_share_buses_take_over_and_route_commands(
    tmp_path: Path, fleet: tuple[Path, str, str]
) -> None:
    fleet_file, key, pg_url = fleet
    gw: dict[str, tuple[Process, str]] = {}
    watch: _WsWatch | None = None
    try:
        for name in ("gw-a", "gw-b"):
            gw[name] = start_gateway(tmp_path, pg_url, fleet_file, name)
        a, b = gw["gw-a"][1], gw["gw-b"][1]

        # Ownership: every bus read by exactly one gateway, shared out two and two.
        def balanced() -> bool:
            oa, ob = _owned(a), _owned(b)
            return len(oa) == 2 and len(ob) == 2 and oa | ob == set(BUSES)

        wait_until(balanced, 90, "both gateways up with two buses each")
        for _ in range(10):  # exclusive at every look, and only leased buses have a reader
            ra, rb = readyz(a), readyz(b)
            assert ra is not None and rb is not None
            oa, ob = set(ra["cluster"]["owned"]), set(rb["cluster"]["owned"])
            assert not oa & ob, (oa, ob)
            assert {x["name"] for x in ra["buses"]} <= oa  # never a reader without the lease
            assert {x["name"] for x in rb["buses"]} <= ob
            for r, mine in ((ra, oa), (rb, ob)):  # each gateway's own view of the owners
                me = r["cluster"]["instance"]
                assert {x for x, o in r["cluster"]["owners"].items() if o == me} == mine
            time.sleep(0.3)
        owned_b = sorted(_owned(b))
        owned_a = sorted(_owned(a))

        # A websocket on gateway A sees live data from a bus that B reads.
        watch = _WsWatch(f"{a.replace('http', 'ws')}/api/v1/ws?key={key}")
        wait_until(
            lambda: watch.seen("live", owned_b[0]), 30, f"live {owned_b[0]} on A's websocket"
        )
        assert watch.seen("snapshot", owned_b[0])

        # Every unit has been heard (status frames in the live view, via A's mirror too).
        headers = {"Authorization": f"Bearer {key}"}

        def online_everywhere() -> bool:
            r = web.get(f"{a}/api/v1/vehicles", headers=headers, timeout=10)
            vs = {v["id"]: v for v in r.json()["vehicles"]}
            return all(vs.get(n, {}).get("online") for n in BUSES)

        wait_until(online_everywhere, 30, "every vehicle online on A")

        # A command posted to A for a bus B reads: B delivers, the simulator confirms.
        target = owned_b[0]
        r = web.post(
            f"{a}/api/v1/vehicles/{target}/commands",
            # SIM-003 has two units: a control reaches both, and says so.
            json={"unit": 30, "jump_start_override": True, "all_units": True},
            headers=headers,
            timeout=10,
        )
        assert r.status_code == 202, r.text
        cid = r.json()["id"]

        def final() -> dict[str, Any] | None:
            got = web.get(f"{a}/api/v1/commands/{cid}", headers=headers, timeout=10).json()
            return got if got["state"] not in ("queued", "sending") else None

        done = wait_until(final, 45, "the command to end")
        assert done["state"] == "confirmed", done
        # A's websocket client followed the command's life from B.
        wait_until(
            lambda: any(
                m.get("type") == "command" and m["data"].get("state") == "confirmed"
                for *_, m in watch.events
            ),
            15,
            "the confirmation on A's websocket",
        )

        # SIGKILL B: its buses move to A within the bound, nothing committed is lost.
        before = _committed(pg_url)
        assert set(before) == set(BUSES), before
        gw["gw-b"][0].kill()
        killed_at = time.time()
        t0 = time.monotonic()
        wait_until(lambda: _owned(a) == set(BUSES), 60, "A to own every bus")
        took = time.monotonic() - t0
        bound = ClusterSettings().takeover_bound_s  # the documented default bound
        assert took < bound, f"takeover took {took:.1f} s (bound {bound:g} s)"
        for bus, (n, newest) in before.items():
            assert _rows_up_to(pg_url, bus, newest) >= n, bus

        # Ingest continues on B's old buses, read by A now (voltages come every 3 s).
        def fresh() -> bool:
            now = _committed(pg_url)
            return all(now[bus][1] > killed_at + 1 for bus in owned_b)

        wait_until(fresh, 30, "new rows on B's old buses after the kill")
        assert all(_committed(pg_url)[bus][1] > killed_at for bus in owned_a)
        wait_until(
            lambda: watch.seen("live", owned_b[-1], after=killed_at + 1),
            30,
            "live data of B's old bus on A's websocket after the kill",
        )
        c = _cluster(a)
        assert c is not None and c["instances"] == ["gw-a"]
        assert c["owners"] == dict.fromkeys(BUSES, "gw-a")
    except AssertionError:
        _diagnose(gw, pg_url)
        raise
    finally:
        if watch is not None:
            watch.close()
        for proc, _ in gw.values():
            proc.stop()


def _terminate_lease_session(pg_url: str, instance: str) -> int:
    """Kill a gateway's lease session from the server side (what a network cut looks like):
    the one of this test's schema only (tests in other schemas run gateways of the same
    names at the same time)."""
    engine = create_engine(pg_url)
    try:
        with engine.begin() as conn:
            database, schema = conn.execute(
                text("SELECT current_database(), current_schema()")
            ).one()
            name = f"{APP_PREFIX}:{namespace_of(database, schema)}:{instance}"[:NAMEDATALEN]
            n = conn.execute(
                text(
                    "SELECT count(pg_terminate_backend(pid)) FROM pg_stat_activity "
                    "WHERE application_name = :name"
                ),
                {"name": name},
            ).scalar_one()
    finally:
        engine.dispose()
    return int(n)


@pytest.mark.postgres
def test_fencing_and_a_bus_only_one_gateway_reaches(
    tmp_path: Path, fleet: tuple[Path, str, str]
) -> None:
    fleet_file, _key, pg_url = fleet
    # SIM-004 is reached through a port of its own (a forwarder to the simulator), which
    # gateway A's network refuses: a firewall between A and that bus, put in A's process
    # (the fleet, in the database, is the same for both gateways).
    text = fleet_file.read_text()
    port = int(text.rsplit("port = ", 1)[1].split()[0])
    forwarder = BlackholeProxy(("127.0.0.1", port))
    blocks = text.split("[[buses]]")
    blocks[-1] = blocks[-1].replace(f"port = {port}", f"port = {forwarder.port}")
    fleet_file.write_text("[[buses]]".join(blocks))
    firewall = tmp_path / "firewall"
    firewall.mkdir()
    (firewall / "sitecustomize.py").write_text(FIREWALL)
    env = {"EQGW_CLUSTER_UNREACHABLE_S": "2"}
    env_a = {
        **env,
        "PYTHONPATH": f"{firewall}{os.pathsep}{ROOT}",
        "EQGW_TEST_REFUSED_PORTS": str(forwarder.port),
    }
    gw: dict[str, tuple[Process, str]] = {}
    try:
        gw["gw-a"] = start_gateway(tmp_path, pg_url, fleet_file, "gw-a", extra_env=env_a)
        gw["gw-b"] = start_gateway(tmp_path, pg_url, fleet_file, "gw-b", extra_env=env)
        a, b = gw["gw-a"][1], gw["gw-b"][1]

        def settled() -> bool:
            oa, ob = _owned(a), _owned(b)
            return "SIM-004" in ob and not oa & ob and oa | ob == set(BUSES) and bool(oa)

        wait_until(settled, 90, "every bus owned, SIM-004 by B (the one that reaches it)")
        start = time.time()
        wait_until(
            lambda: _committed(pg_url).get("SIM-004", (0, 0.0))[1] > start,
            30,
            "SIM-004 ingested by B",
        )

        # A's lease session dies under it: A fences (stops reading everything), B takes over,
        # A rejoins and the buses are shared again.
        assert _terminate_lease_session(pg_url, "gw-a") == 1
        wait_until(lambda: (_cluster(a) or {}).get("fenced", 0) >= 1, 30, "A to fence")
        wait_until(settled, 60, "buses shared again after A rejoined")
        ra, rb = readyz(a), readyz(b)
        assert ra is not None and rb is not None
        # Never a reader without the lease.
        assert {x["name"] for x in ra["buses"]} <= set(ra["cluster"]["owned"])
        assert {x["name"] for x in rb["buses"]} <= set(rb["cluster"]["owned"])
        cut = time.time()
        wait_until(
            lambda: all(v[1] > cut for v in _committed(pg_url).values()),
            30,
            "every bus ingesting after the fencing",
        )
    except AssertionError:
        _diagnose(gw, pg_url)
        raise
    finally:
        for proc, _ in gw.values():
            proc.stop()
        forwarder.close()


# A gateway's network in a test: TCP connections to the ports in EQGW_TEST_REFUSED_PORTS are
# refused, as a firewall would (loaded by the gateway's Python at start: sitecustomize).
FIREWALL = """
import errno, os, socket

_refused = {int(p) for p in os.environ.get("EQGW_TEST_REFUSED_PORTS", "").split(",") if p}
_connect = socket.socket.connect


def connect(self, address):
    if isinstance(address, tuple) and len(address) >= 2 and address[1] in _refused:
        raise ConnectionRefusedError(errno.ECONNREFUSED, "Connection refused (test firewall)")
    return _connect(self, address)


socket.socket.connect = connect
"""


def test_writer_learns_units_another_gateway_registered(engine: Any) -> None:
    """A bus taken over brings units the dead gateway registered after this writer loaded
    the unit ids: their rows are written, not refused."""
    from eqgw.config import WriterSettings
    from eqgw.ingest.writer import BatchedWriter

    writer = BatchedWriter(engine, WriterSettings(flush_ms=20))
    writer.start()
    try:
        writer.put([VehicleRow("V1", {"id": "V1", "name": "V1", "depot": None})])
        writer.put([UnitRow(("V1/can0", 30), "V1"), _m(("V1/can0", 30), 1.0)])
        assert writer.flush(10)
        # Another gateway registers a unit on the same database.
        other = BatchedWriter(engine, WriterSettings(flush_ms=20))
        other.start()
        other.put([UnitRow(("V1/can1", 31), "V1")])
        assert other.flush(10)
        other.stop(10)
        writer.put([_m(("V1/can1", 31), 2.0)])
        assert writer.flush(10)
        assert writer.status().as_dict()["committed_rows"] == 4
    finally:
        assert writer.stop(10) == 0
    with engine.connect() as conn:
        n = conn.execute(text("SELECT count(*) FROM measurements")).scalar_one()
    assert n == 2


def _m(key: tuple[str, int], ts: float) -> MeasurementRow:
    return MeasurementRow(key, {"ts": ts, "v12": 12.6, "v24": 25.2, "i12": 1.0, "i24": 2.0})
