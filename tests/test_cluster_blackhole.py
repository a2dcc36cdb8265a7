"""Two gateways on one PostgreSQL, one of them cut off from it by a blackholed path (packets
dropped, no reset): it must stop sending on its buses, by its own clock, before the other
can take them. Real processes; gateway A reaches the database through a blackholing proxy.

The bus's configuration is the database's, shared by both gateways: once A is cut off, the
bus's `gateway_sa` is changed through B's API (A, cut off, cannot learn it), so that what A
still sends is told apart from B's frames in the bus record."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

import can
import pytest

from tests.cluster_helpers import admin_key, readyz, start_gateway, start_simulator
from tests.proc_helpers import wait_until
from tests.proxy_helpers import blackhole_proxy
from tests.support import web
from tests.test_durability import SERVING

BUS = "SIM-001"
A_SA = 0xF5  # gateway A's source address: its frames are told apart in the bus record


def _fleet(path: Path, port: int, gateway_sa: int) -> Path:
    path.write_text(
        "\n".join(
            [
                "[[vehicles]]",
                f'id = "{BUS}"',
                "",
                "[[buses]]",
                f'name = "{BUS}"',
                f'vehicle_id = "{BUS}"',
                'interface = "socketcand"',
                f'channel = "{BUS}"',
                f'options = {{ host = "127.0.0.1", port = {port} }}',
                f"gateway_sa = {gateway_sa}",
                "",
            ]
        )
    )
    return path


def _bus(port: int) -> dict[str, Any]:
    return {
        "name": BUS,
        "interface": "socketcand",
        "channel": BUS,
        "options": {"host": "127.0.0.1", "port": port},
    }


def _cluster(base: str) -> dict[str, Any] | None:
    body = readyz(base)
    return None if body is None else body.get("cluster")


@pytest.mark.postgres
@pytest.mark.slow
def test_cut_off_gateway_fences_before_another_takes_its_bus(tmp_path: Path, pg_url: str) -> None:
    rec = tmp_path / "rec"
    key = admin_key(pg_url)
    sim, port = start_simulator(tmp_path, 1, "--record", str(rec))
    with blackhole_proxy(pg_url) as proxy:
        a, a_base = start_gateway(
            tmp_path, proxy.url(pg_url), _fleet(tmp_path / "a.toml", port, A_SA), "gw-a"
        )
        b = None
        try:
            a.wait_line(SERVING, timeout=120)
            wait_until(lambda: (c := _cluster(a_base)) and c["owned"] == [BUS], 60, "A owns")
            # B's fleet file is A's: the database holds the bus, as A's file seeded it.
            b, b_base = start_gateway(
                tmp_path, pg_url, _fleet(tmp_path / "b.toml", port, A_SA), "gw-b"
            )
            b.wait_line(SERVING, timeout=120)
            wait_until(
                lambda: (c := _cluster(b_base)) and c["instances"] == ["gw-a", "gw-b"],
                60,
                "B sees both gateways",
            )
            assert _cluster(b_base)["owned"] == []  # type: ignore[index]

            fault = proxy.blackhole()
            # B transmits with another source address from now on; A never hears of it.
            r = web.patch(
                f"{b_base}/api/v1/vehicles/{BUS}",
                json={"buses": [{**_bus(port), "gateway_sa": 0xD8}]},
                headers={"Authorization": f"Bearer {key}"},
                timeout=10,
            )
            assert r.status_code == 200, r.text
            taken = wait_until(
                lambda: (c := _cluster(b_base)) and BUS in c["owned"] and c,
                40,
                "B to take the bus of the cut-off gateway",
            )
            took_at = taken["owned_since"][BUS]
            ca = wait_until(lambda: _cluster(a_base), 20, "A's readiness")
            fenced_at = ca["last_fence_at"]
            sys.stderr.write(
                f"blackholed A: fenced at +{fenced_at - fault:.2f} s, "
                f"B took the bus at +{took_at - fault:.2f} s\n"
            )
            assert ca["owned"] == [] and ca["held"] == [BUS], ca
            assert fenced_at is not None and fault < fenced_at < took_at, (fenced_at, took_at)
        finally:
            for p in (b, a):
                if p is not None:
                    p.stop()
            sim.stop()
    # Nothing A sent reached the bus once B owned it.
    with can.LogReader(str(rec / f"{BUS}.log")) as reader:
        late = [m for m in reader if m.arbitration_id & 0xFF == A_SA and m.timestamp >= took_at]
    assert not late, late[:3]
