"""Two `eqgw serve` on one PostgreSQL schema follow the fleet in the database without a
restart: a vehicle added through one gateway's API has its bus opened and leased by exactly one
gateway within seconds, a PATCH through the other gateway moves it to a new bus, a DELETE
closes it everywhere. The simulated fleet is a real `eqgw simulate` over socketcand.

The seconds from each change to the bus reading frames are printed (run with -s to see them;
`python -m bench.fleet_change` measures them over several rounds)."""

from __future__ import annotations

import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

from tests.cluster_helpers import (
    admin_key,
    readyz,
    start_gateway,
    start_simulator,
    write_fleet,
)
from tests.proc_helpers import Process, wait_until
from tests.support import web

SEEDED = ["SIM-001", "SIM-002"]  # in the fleet file
ADDED = "SIM-003"  # added through the API


@pytest.fixture
def cluster(tmp_path: Path, pg_url: str) -> Iterator[dict[str, Any]]:
    """A 3-vehicle simulator, a fleet file with two of them, two gateways, an admin key."""
    key = admin_key(pg_url)
    sim, port = start_simulator(tmp_path, 3)
    fleet = write_fleet(tmp_path / "fleet.toml", SEEDED, port)
    gws: dict[str, tuple[Process, str]] = {}
    try:
        for name in ("gw-a", "gw-b"):
            gws[name] = start_gateway(tmp_path, pg_url, fleet, name)
        yield {"key": key, "port": port, "gws": gws}
    finally:
        for proc, _ in gws.values():
            proc.stop()
        sim.stop()


def _owners(bases: list[str]) -> dict[str, list[str]]:
    """Per bus, the gateways that say they own it now."""
    out: dict[str, list[str]] = {}
    for base in bases:
        body = readyz(base) or {}
        c = body.get("cluster") or {}
        for bus in c.get("owned", []):
            out.setdefault(bus, []).append(c["instance"])
    return out


def _reading(bases: list[str], bus: str) -> list[str]:
    """The gateways with a reader of `bus` (in /readyz's buses)."""
    out = []
    for base in bases:
        body = readyz(base) or {}
        if any(b["name"] == bus for b in body.get("buses") or []):
            out.append(base)
    return out


def _heard_after(base: str, key: str, vehicle: str, bus: str, after: float) -> bool:
    r = web.get(
        f"{base}/api/v1/vehicles/{vehicle}/live",
        headers={"Authorization": f"Bearer {key}"},
        timeout=10,
    )
    if r.status_code != 200:
        return False
    units = r.json().get("units", [])
    return any(u.get("bus") == bus and (u.get("last_seen") or 0) > after for u in units)


def _once_exclusive(bases: list[str], bus: str, seen: list[str]) -> Callable[[], bool]:
    """A wait condition: `bus` owned by exactly one gateway (never two at any look)."""

    def check() -> bool:
        owners = _owners(bases).get(bus, [])
        assert len(owners) <= 1, f"{bus} owned by {owners}"
        if owners:
            seen[:] = owners
        return len(owners) == 1

    return check


@pytest.mark.postgres
def test_two_gateways_follow_vehicles_added_changed_and_deleted(
    cluster: dict[str, Any],
) -> None:
    key, port, gws = cluster["key"], cluster["port"], cluster["gws"]
    a, b = gws["gw-a"][1], gws["gw-b"][1]
    bases = [a, b]
    auth = {"Authorization": f"Bearer {key}"}
    try:
        # Both serving first: one gateway alone can lease every seeded bus while the other
        # is still starting (its API then refuses the connection).
        wait_until(lambda: all(readyz(base) is not None for base in bases), 120, "both serving")
        wait_until(lambda: set(_owners(bases)) == set(SEEDED), 120, "the seeded buses leased")

        # Added through A: exactly one gateway leases and reads it, within seconds.
        bus = {
            "name": ADDED,
            "interface": "socketcand",
            "channel": ADDED,
            "options": {"host": "127.0.0.1", "port": port},
        }
        t0 = time.time()
        r = web.post(
            f"{a}/api/v1/vehicles",
            json={"id": ADDED, "name": "Added", "depot": "North", "buses": [bus]},
            headers=auth,
            timeout=10,
        )
        assert r.status_code == 201, r.text
        version = r.json()["version"]
        owner: list[str] = []
        wait_until(_once_exclusive(bases, ADDED, owner), 30, f"{ADDED} leased by one gateway")
        leased_s = time.time() - t0
        owner_base = a if owner[0] == "gw-a" else b
        wait_until(lambda: _heard_after(owner_base, key, ADDED, ADDED, t0), 30, "frames")
        frames_s = time.time() - t0
        # B learned of it as well (told at once, or by its poll), whichever reads it.
        wait_until(lambda: (readyz(b) or {}).get("fleet", {}).get("version") == version, 10,
                   "B on the new fleet version")  # fmt: skip
        assert _reading(bases, ADDED) == [owner_base]
        for _ in range(5):  # exclusive at every look
            assert len(_owners(bases).get(ADDED, [])) == 1
            time.sleep(0.2)
        listed = web.get(f"{b}/api/v1/vehicles", headers=auth, timeout=10).json()
        assert ADDED in {v["id"] for v in listed["vehicles"]}

        # Changed through B: the bus is renamed and the vehicle moves depot; the old bus is
        # closed everywhere, the new one read by exactly one gateway.
        renamed = f"{ADDED}/b"
        t1 = time.time()
        r = web.patch(
            f"{b}/api/v1/vehicles/{ADDED}",
            json={"depot": "South", "buses": [{**bus, "name": renamed}]},
            headers=auth,
            timeout=10,
        )
        assert r.status_code == 200, r.text
        assert r.json()["depot"] == "South" and [x["name"] for x in r.json()["buses"]] == [renamed]
        wait_until(_once_exclusive(bases, renamed, owner), 30, f"{renamed} leased by one")
        owner_base = a if owner[0] == "gw-a" else b
        wait_until(lambda: _heard_after(owner_base, key, ADDED, renamed, t1), 30, "frames")
        patch_frames_s = time.time() - t1
        wait_until(lambda: ADDED not in _owners(bases) and not _reading(bases, ADDED), 15,
                   f"the old bus {ADDED} closed everywhere")  # fmt: skip

        # Deleted through A: closed on every gateway, gone from both listings.
        t2 = time.time()
        r = web.delete(f"{a}/api/v1/vehicles/{ADDED}", headers=auth, timeout=10)
        assert r.status_code == 200, r.text
        wait_until(lambda: renamed not in _owners(bases) and not _reading(bases, renamed), 15,
                   f"{renamed} closed everywhere")  # fmt: skip
        closed_s = time.time() - t2
        for base in bases:

            def gone(base: str = base) -> bool:
                r = web.get(f"{base}/api/v1/vehicles", headers=auth, timeout=10)
                return ADDED not in {v["id"] for v in r.json()["vehicles"]}

            wait_until(gone, 10, f"{ADDED} gone from {base}'s listing")
        # The seeded buses were never disturbed.
        assert set(_owners(bases)) == set(SEEDED)
        sys.stderr.write(
            f"fleet change timings: POST->leased {leased_s:.2f} s, POST->frames "
            f"{frames_s:.2f} s, PATCH->frames on the new bus {patch_frames_s:.2f} s, "
            f"DELETE->closed everywhere {closed_s:.2f} s\n"
        )
    except AssertionError:
        for name, (proc, base) in gws.items():
            sys.stderr.write(f"--- {name}: {readyz(base)}\n{proc.output()[-4000:]}\n")
        raise
