"""Two `eqgw serve` on one PostgreSQL take commands for the same vehicle at the same moment:
the database serializes them. Of two conflicting commands exactly one is accepted (409 for the
other), and one Idempotency-Key sent to both gateways at once gives one command, never a 5xx.
Real parts: a simulator over socketcand, two gateway processes, the shared PostgreSQL."""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
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


@dataclass
class Pair:
    """Two gateways on one schema, each reading one bus, and an operator key."""

    a: str
    b: str
    key: str
    procs: list[tuple[Process, str]]

    def diagnose(self) -> str:
        """How each gateway sees the buses and SIM-001, and what it logged about them."""
        out = []
        for proc, base in self.procs:
            try:
                r = web.get(
                    f"{base}/api/v1/vehicles/SIM-001/live",
                    headers={"Authorization": f"Bearer {self.key}"},
                    timeout=10,
                )
                units = [
                    {k: u.get(k) for k in ("sa", "online", "state", "last_seen", "parked_since")}
                    | {"faults": [f.get("fault") for f in u.get("faults", [])]}
                    for u in r.json().get("units", [])
                ]
                vehicle = f"{r.status_code} {units}"
            except (httpx.HTTPError, ValueError) as exc:
                vehicle = repr(exc)
            cluster = (readyz(base) or {}).get("cluster") or {}
            keys = ("owned", "held", "owners", "takeovers", "fenced", "last_error")
            lease = {k: cluster.get(k) for k in keys}
            said = [
                line
                for line in proc.output().splitlines()
                if "cluster" in line or " WARNING " in line or " ERROR " in line
            ]
            out.append(
                f"--- {base} at {time.time():.3f}: cluster {lease}\n"
                f"SIM-001 {vehicle}\n" + "\n".join(said[-30:])
            )
        return "\n".join(out)

    @contextmanager
    def explained(self) -> Iterator[None]:
        """A failed assertion inside says how both gateways saw things, in its message."""
        try:
            yield
        except AssertionError as exc:
            raise AssertionError(f"{exc}\n{self.diagnose()}") from None


@pytest.fixture
def gateways(tmp_path: Path, pg_url: str) -> Iterator[Pair]:
    """A simulator and two gateways on one schema, each reading one bus."""
    key = operator_key(pg_url, "race")
    sim, port = start_simulator(tmp_path, len(BUSES))
    fleet = write_fleet(tmp_path / "fleet.toml", BUSES, port)
    # Info: which gateway reads which bus, and when that changed, is in a failure's report.
    env = {"EQGW_API_WRITE_RATE": "1000", "EQGW_LOG_LEVEL": "info"}
    gw: list[tuple[Process, str]] = []
    try:
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
        except AssertionError as exc:
            raise AssertionError(f"{exc}\n{Pair('', '', key, gw).diagnose()}") from None
        yield Pair(a, b, key, gw)
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


def test_conflicting_commands_through_two_gateways_one_wins(gateways: Pair) -> None:
    a, b, key = gateways.a, gateways.b, gateways.key
    with gateways.explained():
        headers = {"Authorization": f"Bearer {key}"}
        outcomes: list[tuple[int, int]] = []
        for _ in range(ROUNDS):
            ra, rb = _race(
                [
                    (
                        f"{a}/api/v1/vehicles/SIM-001/commands",
                        {"jump_start_override": True},
                        headers,
                    ),
                    (
                        f"{b}/api/v1/vehicles/SIM-001/commands",
                        {"jump_start_override": False},
                        headers,
                    ),
                ]
            )
            outcomes.append((ra.status_code, rb.status_code))
            for base, r in ((a, ra), (b, rb)):
                if r.status_code == 202:
                    _cancel(base, r.json()["id"], headers)
                else:
                    assert r.status_code == 409 and r.json()["type"] == "conflict", r.text
        assert all(sorted(o) == [202, 409] for o in outcomes), outcomes


def test_one_idempotency_key_through_two_gateways_one_command(gateways: Pair) -> None:
    a, b, key = gateways.a, gateways.b, gateways.key
    with gateways.explained():
        outcomes: list[tuple[int, int]] = []
        refusals: list[str] = []  # what a refusal said, for the failure's message
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
            refusals += [f"round {i}: {r.status_code} {r.text}" for r in rs if r.status_code != 202]
            got = {r.json()["id"] for r in rs if r.status_code == 202}
            ids.append(got)
            for cid in got:
                _cancel(a, cid, {"Authorization": f"Bearer {key}"})
        assert all(o == (202, 202) for o in outcomes), (outcomes, refusals[:4])
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
