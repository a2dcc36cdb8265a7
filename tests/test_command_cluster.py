"""Two `eqgw serve` on one PostgreSQL take commands for the same vehicle at the same moment:
the database serializes them. Of two conflicting commands exactly one is accepted (409 for the
other), and one Idempotency-Key sent to both gateways at once gives one command, never a 5xx.
Real parts: a simulator over socketcand, two gateway processes, the shared PostgreSQL."""

from __future__ import annotations

import sys
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest
from sqlalchemy import Engine, text
from sqlalchemy.exc import OperationalError

from eqgw.commands import repository as q
from eqgw.store.engine import create_engine
from tests.cluster_helpers import operator_key, readyz, start_gateway, start_simulator, write_fleet
from tests.proc_helpers import Process, wait_until
from tests.support import web

pytestmark = pytest.mark.postgres

BUSES = ["SIM-001", "SIM-002"]
ROUNDS = 20


@pytest.fixture
def gateways(tmp_path: Path, pg_url: str) -> Iterator[tuple[str, str, str]]:
    """A simulator and two gateways on one schema, each reading one bus; (A, B, operator key)."""
    key = operator_key(pg_url, "race")
    sim, port = start_simulator(tmp_path, len(BUSES))
    fleet = write_fleet(tmp_path / "fleet.toml", BUSES, port)
    env = {"EQGW_API_WRITE_RATE": "1000"}
    gw: list[tuple[Process, str]] = []
    try:
        for name in ("gw-a", "gw-b"):
            gw.append(start_gateway(tmp_path, pg_url, fleet, name, extra_env=env))
        a, b = gw[0][1], gw[1][1]
        headers = {"Authorization": f"Bearer {key}"}

        def owned(base: str) -> set[str]:
            body = readyz(base)
            return set(body["cluster"]["owned"]) if body and body.get("cluster") else set()

        wait_until(lambda: len(owned(a)) == len(owned(b)) == 1, 90, "a bus for each gateway")

        def online(base: str) -> bool:
            r = web.get(f"{base}/api/v1/vehicles", headers=headers, timeout=10)
            vs = {v["id"]: v for v in r.json()["vehicles"]}
            return all(vs.get(n, {}).get("online") for n in BUSES)

        wait_until(lambda: online(a) and online(b), 60, "every vehicle online on both")
        yield a, b, key
    except AssertionError:
        for proc, base in gw:
            sys.stderr.write(f"--- {base}: readyz {readyz(base)}\n{proc.output()[-4000:]}\n")
        raise
    finally:
        for proc, _ in gw:
            proc.stop()
        sim.stop()


def _race(posts: list[tuple[str, dict[str, Any], dict[str, str]]]) -> list[httpx.Response]:
    """POST each (url, body, headers) from its own thread, all released at once."""
    barrier = threading.Barrier(len(posts))
    out: list[httpx.Response | BaseException] = [RuntimeError("not run")] * len(posts)

    def run(i: int) -> None:
        url, body, headers = posts[i]
        with web.Client(timeout=30) as client:
            client.get(url.split("/api/")[0] + "/healthz")  # connected before the start line
            barrier.wait(timeout=30)
            try:
                out[i] = client.post(url, json=body, headers=headers)
            except BaseException as exc:
                out[i] = exc

    threads = [threading.Thread(target=run, args=(i,)) for i in range(len(posts))]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=60)
    for r in out:
        if isinstance(r, BaseException):
            raise r
    return [r for r in out if isinstance(r, httpx.Response)]


def _cancel(base: str, cid: str, headers: dict[str, str]) -> None:
    r = web.delete(f"{base}/api/v1/commands/{cid}", headers=headers, timeout=30)
    # A control the simulator confirmed at once has ended already: nothing left to cancel.
    assert r.status_code in (200, 409), r.text


def test_conflicting_commands_through_two_gateways_one_wins(
    gateways: tuple[str, str, str],
) -> None:
    a, b, key = gateways
    headers = {"Authorization": f"Bearer {key}"}
    outcomes: list[tuple[int, int]] = []
    for _ in range(ROUNDS):
        ra, rb = _race(
            [
                (f"{a}/api/v1/vehicles/SIM-001/commands", {"jump_start_override": True}, headers),
                (f"{b}/api/v1/vehicles/SIM-001/commands", {"jump_start_override": False}, headers),
            ]
        )
        outcomes.append((ra.status_code, rb.status_code))
        for base, r in ((a, ra), (b, rb)):
            if r.status_code == 202:
                _cancel(base, r.json()["id"], headers)
            else:
                assert r.status_code == 409 and r.json()["type"] == "conflict", r.text
    assert all(sorted(o) == [202, 409] for o in outcomes), outcomes


def test_one_idempotency_key_through_two_gateways_one_command(
    gateways: tuple[str, str, str],
) -> None:
    a, b, key = gateways
    outcomes: list[tuple[int, int]] = []
    ids: list[set[str]] = []
    for i in range(ROUNDS):
        headers = {"Authorization": f"Bearer {key}", "Idempotency-Key": f"race-{i}"}
        body = {"can_onoff_enable": True}
        rs = _race(
            [
                (f"{a}/api/v1/vehicles/SIM-002/commands", body, headers),
                (f"{b}/api/v1/vehicles/SIM-002/commands", body, headers),
            ]
        )
        outcomes.append((rs[0].status_code, rs[1].status_code))
        got = {r.json()["id"] for r in rs if r.status_code == 202}
        ids.append(got)
        for cid in got:
            _cancel(a, cid, {"Authorization": f"Bearer {key}"})
    assert all(o == (202, 202) for o in outcomes), outcomes
    assert all(len(x) == 1 for x in ids), ids


def _locks(engine: Engine, bus: str, idem: tuple[int, str] | None = None) -> bool:
    """Whether this session gets the command queue lock of `bus` within 0.3 s."""
    try:
        with engine.begin() as conn:
            conn.execute(text("SET LOCAL lock_timeout = '300ms'"))
            q.lock_command_queue(conn, bus, idem)
    except OperationalError as exc:
        assert "lock timeout" in str(exc), exc
        return False
    return True


def test_the_queue_lock_is_per_bus_key_and_schema(pg_url: str) -> None:
    other_schema = f"{pg_url.rsplit('%3D', 1)[1]}_other"
    engine = create_engine(pg_url)
    other = create_engine(pg_url.replace(pg_url.rsplit("%3D", 1)[1], other_schema))
    try:
        with engine.begin() as conn:
            conn.execute(text(f'CREATE SCHEMA "{other_schema}"'))
        with engine.begin() as holder:
            q.lock_command_queue(holder, "V1/can0", (7, "k-1"))
            # Held until the transaction ends: the same bus waits, the same key waits.
            assert not _locks(engine, "V1/can0")
            assert not _locks(engine, "V2/can0", (7, "k-1"))
            # Another bus, another key, or the same bus in another schema: no wait.
            assert _locks(engine, "V2/can0", (7, "k-2"))
            assert _locks(engine, "V1/can1")
            assert _locks(other, "V1/can0", (7, "k-1"))
        assert _locks(engine, "V1/can0", (7, "k-1"))  # released with the transaction
    finally:
        with engine.begin() as conn:
            conn.execute(text(f'DROP SCHEMA IF EXISTS "{other_schema}" CASCADE'))
            conn.execute(text(f'DROP SCHEMA IF EXISTS "{other_schema}_partitions" CASCADE'))
        other.dispose()
        engine.dispose()
