"""Control and parameter frames are broadcasts (PDU2: every equalizer on the bus applies them):
the API writes to a bus, says which units it reaches, validates and checks conflicts for all
of them, and confirms a control command only once every one shows it. Real parts: the app, the
simulator (whose units follow the manual: each applies every frame on its bus), SQLite and
PostgreSQL; every write is read back through the simulated units' own parameters."""

from __future__ import annotations

from typing import Any

from eqgw.ingest.events import Event
from eqgw.ingest.faults import OFFLINE
from eqgw.sim.equalizer import EqualizerSpec
from eqgw.sim.vehicle import VehicleSpec
from tests.api_helpers import Served, served, wait_for

V = "/api/v1/vehicles"
PAIR = "SIM-003"  # the generated fleet's third vehicle: two 80-series units, SA 30 and 31
BUS = f"{PAIR}/sim"
REACHES = f"this write reaches every equalizer on bus {BUS} (units 30, 31)"


async def _ended(s: Served, cid: str) -> dict[str, Any]:
    async def done() -> dict[str, Any] | None:
        r = await s.client.get(f"/api/v1/commands/{cid}", headers=s.auth())
        body: dict[str, Any] = r.json()
        return body if body["state"] not in ("queued", "sending") else None

    ended: dict[str, Any] = await wait_for(done, 60, what=f"command {cid} to end")
    return ended


def _params(s: Served, vehicle: str, sa: int) -> dict[str, Any]:
    params: dict[str, Any] = s.sim.vehicle(vehicle).unit(sa).params
    return params


async def test_a_parameter_write_names_every_unit_it_reaches(db_url: str) -> None:
    # Eight sends (7 s at least): the first write is surely pending while the next ones come.
    async with served(db_url, parameter_sends=8) as s:
        c = s.client
        op = s.auth(await s.key("operator"))
        events = s.rt.commands.hub.subscribe(None, maxsize=1000)

        async def identified() -> bool:  # the gateway asks each unit for its component ID
            units = s.rt.ingest.live.of_vehicle(PAIR)
            return sorted((u.ref.sa, u.series) for u in units) == [(30, 80), (31, 80)]

        await wait_for(identified, 60, what="both units' series")
        assert _params(s, PAIR, 30)["ov_setpoint_v"] == _params(s, PAIR, 31)["ov_setpoint_v"]
        before = _params(s, PAIR, 30)["ov_setpoint_v"]
        # "For unit 31" is not a thing the bus knows: refused, saying what the write reaches.
        for body in ({"unit": 31, "ov_setpoint_v": 35.0}, {"ov_setpoint_v": 35.0},
                     {"unit": 30, "ov_setpoint_v": 35.0, "all_units": False}):  # fmt: skip
            r = await c.post(f"{V}/{PAIR}/parameters", json=body, headers=op)
            assert r.status_code == 422, r.text
            assert r.json()["type"] == "all_units_required"
            assert REACHES in r.json()["detail"], r.json()
        assert _params(s, PAIR, 30)["ov_setpoint_v"] == before  # nothing was sent
        # Said knowingly, it is accepted, and the answer lists the units with their series.
        r = await c.post(
            f"{V}/{PAIR}/parameters", json={"ov_setpoint_v": 35.0, "all_units": True}, headers=op
        )
        assert r.status_code == 202, r.text
        cmd = r.json()
        affected = [{"sa": 30, "series": 80}, {"sa": 31, "series": 80}]
        assert cmd["affected_units"] == affected and cmd["bus"] == BUS
        # A different value "for the other unit" would fight on the bus: a conflict per bus.
        r = await c.post(
            f"{V}/{PAIR}/parameters",
            json={"unit": 31, "ov_setpoint_v": 36.0, "all_units": True},
            headers=op,
        )
        assert r.status_code == 409 and r.json()["command_id"] == cmd["id"], r.text
        # So would a factory reset, which puts every parameter of both units back.
        r = await c.post(
            f"{V}/{PAIR}/parameters",
            json={"unit": 31, "factory_reset": True, "all_units": True},
            headers=op,
        )
        assert r.status_code == 409 and r.json()["type"] == "conflict", r.text
        done = await _ended(s, cmd["id"])
        assert done["state"] == "sent" and done["affected_units"] == affected
        # Read back from the simulated units: both took it.
        assert _params(s, PAIR, 30)["ov_setpoint_v"] == 35.0
        assert _params(s, PAIR, 31)["ov_setpoint_v"] == 35.0
        # The websocket's command events and the audit log carry the units too.
        published: list[Event] = []
        while (ev := events.get_nowait()) is not None:
            published.append(ev)
        events.close()
        mine = [ev.data for ev in published if ev.kind == "command" and ev.data["id"] == cmd["id"]]
        assert mine and all(d["affected_units"] == affected for d in mine)
        audit = (await c.get("/api/v1/audit", headers=op)).json()["entries"]
        entries = [e for e in audit if e["command_id"] == cmd["id"]]
        assert {e["target"] for e in entries} == {f"{BUS}/30,31"}, entries
        accepted = next(e for e in entries if e["outcome"] == "accepted")
        assert "units 30 (80-series), 31 (80-series)" in accepted["detail"]
        # A vehicle with one unit needs no acknowledgement and lists that unit.
        r = await c.post(f"{V}/SIM-001/parameters", json={"fault_timer_s": 12}, headers=op)
        assert r.status_code == 202 and r.json()["affected_units"] == [{"sa": 30, "series": 80}]


async def test_control_is_confirmed_only_when_every_unit_shows_it(db_url: str) -> None:
    async with served(db_url) as s:
        c = s.client
        op = s.auth(await s.key("operator"))
        r = await c.post(f"{V}/{PAIR}/commands", json={"jump_start_override": True}, headers=op)
        assert r.status_code == 422 and r.json()["type"] == "all_units_required", r.text
        assert REACHES in r.json()["detail"]
        # Both units act on it and both status flags confirm it.
        body = {"jump_start_override": True, "all_units": True}
        r = await c.post(f"{V}/{PAIR}/commands", json=body, headers=op)
        assert r.status_code == 202, r.text
        assert [u["sa"] for u in r.json()["affected_units"]] == [30, 31]
        done = await _ended(s, r.json()["id"])
        assert done["state"] == "confirmed", done
        veh = s.sim.vehicle(PAIR)
        assert veh.unit(30).jso and veh.unit(31).jso
        # Unit 31's receive path fails: unit 30's flags alone never confirm the command.
        veh.ignore_commands(31)
        body = {"jump_start_override": False, "all_units": True, "expires_in_s": 6}
        r = await c.post(f"{V}/{PAIR}/commands", json=body, headers=op)
        assert r.status_code == 202, r.text
        done = await _ended(s, r.json()["id"])
        assert not veh.unit(30).jso and veh.unit(31).jso
        assert done["state"] != "confirmed" and done["sends"] >= 2, done


async def test_a_write_one_unit_on_the_bus_cannot_take_is_refused_naming_it(db_url: str) -> None:
    mixed = VehicleSpec(
        name="MIX-1", units=[EqualizerSpec(sa=30, series=80), EqualizerSpec(sa=31, series=70)]
    )
    async with served(db_url, [mixed]) as s:
        c = s.client
        op = s.auth(await s.key("operator"))

        async def identified() -> bool:  # the gateway asks each unit for its component ID
            units = s.rt.ingest.live.of_vehicle("MIX-1")
            return sorted((u.ref.sa, u.series) for u in units) == [(30, 80), (31, 70)]

        await wait_for(identified, 60, what="both units' series")
        # An 80-series parameter would reach the 70-series unit too.
        r = await c.post(
            f"{V}/MIX-1/parameters",
            json={"unit": 30, "capacity_ah": 150, "all_units": True},
            headers=op,
        )
        assert r.status_code == 422 and r.json()["type"] == "unsupported_field", r.text
        assert "unit 31" in r.json()["detail"] and "70-series" in r.json()["detail"]
        assert "unit 30" not in r.json()["detail"]
        # Smart Sensor messages exist on the 70-series only: unit 30 is named.
        r = await c.post(
            f"{V}/MIX-1/commands",
            json={"smart_sensor_messages": False, "all_units": True},
            headers=op,
        )
        assert r.status_code == 422 and "unit 30" in r.json()["detail"], r.text
        # What both series take goes to both, read back from each.
        r = await c.post(
            f"{V}/MIX-1/parameters", json={"uv_setpoint_v": 22.5, "all_units": True}, headers=op
        )
        assert r.status_code == 202, r.text
        assert r.json()["affected_units"] == [{"sa": 30, "series": 80}, {"sa": 31, "series": 70}]
        assert (await _ended(s, r.json()["id"]))["state"] == "sent"
        assert _params(s, "MIX-1", 30)["uv_setpoint_v"] == 22.5
        assert _params(s, "MIX-1", 31)["uv_setpoint_v"] == 22.5
        # An offline unit on the bus would miss the write: refused, naming it. (Unit 31's
        # own wiring cut: the rest of the bus talks on, so the gateway finds it offline.)
        st = s.rt.ingest.live.get("MIX-1/sim", 31)
        assert st is not None
        s.sim.disconnect_unit("MIX-1", 31)
        try:

            async def offline() -> bool:
                return OFFLINE in st.faults.open

            await wait_for(offline, 60, what="unit 31 offline")
            r = await c.post(
                f"{V}/MIX-1/parameters", json={"uv_setpoint_v": 23.0, "all_units": True},
                headers=op,
            )  # fmt: skip
            assert r.status_code == 409 and r.json()["type"] == "unit_offline", r.text
            assert "unit 31" in r.json()["detail"]
        finally:
            s.sim.reconnect_unit("MIX-1", 31)
