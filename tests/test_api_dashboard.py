"""The API pieces the dashboard needs: `/me`, the parameter catalogue, SOH and diagnosis in the
fleet summary, and the status-flag history."""

from __future__ import annotations

import time

from tests.api_helpers import served, wait_for

API = "/api/v1"


async def test_me_parameters_summary_and_status_history(sqlite_url: str) -> None:
    async with served(sqlite_url, vehicles=2) as s:
        c = s.client
        assert (await c.get(f"{API}/me")).status_code == 401
        viewer = await s.key("viewer", "office")
        r = await c.get(f"{API}/me", headers=s.auth(viewer))
        assert r.status_code == 200
        assert r.json()["role"] == "viewer" and r.json()["name"] == "office"
        assert (await c.get(f"{API}/me", headers=s.auth())).json()["role"] == "admin"

        r = await c.get(f"{API}/parameters", headers=s.auth(viewer))
        params = {p["name"]: p for p in r.json()["parameters"]}
        ov = params["ov_setpoint_v"]
        assert ov["unit"] == "V" and ov["minimum"] < ov["maximum"] and 70 in ov["series"]

        r = await c.get(f"{API}/vehicles", headers=s.auth(viewer))
        unit = r.json()["vehicles"][0]["units"][0]
        assert {"soh_12v", "soh_24v", "faults"} <= set(unit)
        assert unit["diagnosis"]["condition"] in (
            "unknown", "standby", "normal", "overload", "equalizer_not_functioning",
            "abnormal", "shutdown_risk",
        )  # fmt: skip
        assert unit["diagnosis"]["text"]

        async def stored() -> bool:
            r = await c.get(
                f"{API}/vehicles/SIM-001/status",
                params={"from": time.time() - 600},
                headers=s.auth(viewer),
            )
            return r.status_code == 200 and bool(r.json()["changes"])

        await wait_for(stored, what="a stored status change")
        r = await c.get(
            f"{API}/vehicles/SIM-001/status",
            params={"from": time.time() - 600},
            headers=s.auth(viewer),
        )
        change = r.json()["changes"][0]
        assert change["flags"]["eqrn"] in ("active", "inactive") and "ts" in change
        r = await c.get(
            f"{API}/vehicles/SIM-001/status", params={"from": 10, "to": 5}, headers=s.auth(viewer)
        )
        assert r.status_code == 422
        r = await c.get(f"{API}/vehicles/NOPE/status", headers=s.auth(viewer))
        assert r.status_code == 404
