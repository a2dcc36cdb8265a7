"""Vehicles managed without a restart, on SQLite and PostgreSQL: created, changed and deleted
through the API (the gateway opens, reopens and closes the bus at once: a real python-can
virtual bus fed by the simulated fleet), imported from CSV (every bad row with its line
number, a dry run that changes nothing, one transaction), limited to a scoped admin's depots,
audited; `eqgw vehicles import` and `export`; the fleet file seeds an empty database only."""

from __future__ import annotations

import asyncio
import logging
import time
from pathlib import Path
from typing import Any

import pytest

from eqgw.bus.config import BusConfig
from eqgw.cli import main as eqgw_main
from eqgw.config import Settings, VehicleConfig
from eqgw.fleet import registry
from eqgw.main import create_app
from eqgw.store.engine import create_engine
from eqgw.web.settings import ApiSettings
from tests.api_helpers import Served, lifespan, served, wait_for

V = "/api/v1/vehicles"
CSV = {"content-type": "text/csv"}
DEPOTS = {"SIM-001": "north", "SIM-002": "north", "SIM-003": "south"}


def _depots_config() -> dict[str, Any]:
    return {"vehicles": [VehicleConfig(id=v, name=v, depot=d) for v, d in DEPOTS.items()]}


def _bus(name: str, channel: str, **more: Any) -> dict[str, Any]:
    """A virtual bus on a simulated vehicle's channel (it hears that vehicle's units); no
    address claim, so it does not contend with the simulated vehicle's own bus."""
    return {
        "name": name,
        "interface": "virtual",
        "channel": channel,
        "bitrate": None,
        "address_claim": False,
        **more,
    }


async def _units_on(s: Served, bus: str) -> bool:
    return any(u.ref.bus == bus and u.last_seen for u in s.rt.ingest.live.units.values())


async def _audit(s: Served, action: str) -> list[dict[str, Any]]:
    r = await s.client.get("/api/v1/audit", params={"limit": 1000}, headers=s.auth())
    return [e for e in r.json()["entries"] if e["action"] == action]


async def test_a_vehicle_is_added_changed_and_deleted_without_a_restart(db_url: str) -> None:
    async with served(db_url, vehicles=1) as s:
        channel = s.sim.vehicles["SIM-001"].channel
        body = {"id": "NEW-1", "name": "New one", "depot": "north",
                "buses": [_bus("NEW-1/can0", channel)]}  # fmt: skip
        t0 = time.monotonic()
        r = await s.client.post(V, json=body, headers=s.auth())
        assert r.status_code == 201, r.text
        made = r.json()
        assert made["version"] >= 1 and made["buses"][0]["equalizer_sas"] == [30]
        assert made["buses"][0]["address_claim_name"] is None
        # Opened at once: its units heard, in the live view and the listing.
        await wait_for(lambda: _units_on(s, "NEW-1/can0"), what="units on the new bus")
        logging.getLogger("test").warning("POST -> frames in-process: %.2f s",
                                          time.monotonic() - t0)  # fmt: skip
        assert "NEW-1/can0" in s.rt.ingest.reading()
        listed = (await s.client.get(V, headers=s.auth())).json()["vehicles"]
        assert {"NEW-1", "SIM-001"} <= {v["id"] for v in listed}
        live = await s.client.get(f"{V}/NEW-1/live", headers=s.auth())
        assert live.status_code == 200 and live.json()["units"], live.text
        got = await s.client.get(f"{V}/NEW-1/config", headers=s.auth())
        assert got.status_code == 200 and got.json() == made

        # A changed bus is reopened: renamed, the old one closed and its units gone.
        r = await s.client.patch(
            f"{V}/NEW-1",
            json={"depot": "south", "buses": [_bus("NEW-1/can1", channel, gateway_sa=0xD9)]},
            headers=s.auth(),
        )
        assert r.status_code == 200, r.text
        assert r.json()["depot"] == "south" and r.json()["name"] == "New one"
        assert r.json()["version"] == made["version"] + 1
        await wait_for(lambda: _units_on(s, "NEW-1/can1"), what="units on the renamed bus")
        assert "NEW-1/can0" not in s.rt.ingest.reading()
        assert not await _units_on(s, "NEW-1/can0")
        # Only the name: the buses stay as they are (not reopened).
        r = await s.client.patch(f"{V}/NEW-1", json={"name": None}, headers=s.auth())
        assert r.status_code == 200 and r.json()["name"] == "NEW-1", r.text
        assert [b["gateway_sa"] for b in r.json()["buses"]] == [0xD9]

        # Deleted: the bus closes, the vehicle leaves every listing; its history stays.
        r = await s.client.delete(f"{V}/NEW-1", headers=s.auth())
        assert r.status_code == 200 and r.json()["id"] == "NEW-1", r.text
        assert "NEW-1/can1" not in s.rt.ingest.reading()
        assert not s.rt.ingest.live.of_vehicle("NEW-1")
        listed = (await s.client.get(V, headers=s.auth())).json()["vehicles"]
        assert "NEW-1" not in {v["id"] for v in listed}
        for method in ("GET", "DELETE"):
            r = await s.client.request(method, f"{V}/NEW-1/config" if method == "GET"
                                       else f"{V}/NEW-1", headers=s.auth())  # fmt: skip
            assert r.status_code == 404 and r.json()["type"] == "unknown_vehicle", r.text
        # Created again, with its old bus name: its history is its own again.
        body["buses"] = [_bus("NEW-1/can0", channel)]
        r = await s.client.post(V, json=body, headers=s.auth())
        assert r.status_code == 201, r.text
        await wait_for(lambda: _units_on(s, "NEW-1/can0"), what="units after re-creating")
        # Every change audited, with who did it.
        for action in ("vehicle.create", "vehicle.update", "vehicle.delete"):
            entries = [e for e in await _audit(s, action) if e["outcome"] == "accepted"]
            assert entries, action
            assert entries[0]["vehicle_id"] == "NEW-1" and entries[0]["key_name"] == "first admin"


async def test_refusals_name_the_reason(db_url: str) -> None:
    async with served(db_url, vehicles=1) as s:
        ch = s.sim.vehicles["SIM-001"].channel

        async def stored() -> bool:  # the simulated units' rows written
            units = await s.rt.db(lambda conn: list(registry.repo.history_owners(conn, [
                "SIM-001/sim"])))  # fmt: skip
            return bool(units)

        await wait_for(stored, what="the units stored")
        cases: list[tuple[dict[str, Any], int, str]] = [
            ({"id": "SIM-001"}, 409, "exists"),
            ({"id": "X/1"}, 422, "no '/'"),
            ({"id": "X1", "buses": [_bus("X1/a", ch, interface="nope")]}, 422, "interface"),
            ({"id": "X1", "buses": [_bus("X1/a", ch, equalizer_sas=[300])]}, 422, "0..253"),
            ({"id": "X1", "buses": [_bus("X1/a", ch, options={"channel": "x"})]}, 422, "option"),
            ({"id": "X1", "buses": [_bus("SIM-001/sim", ch)]}, 409, "history of another"),
            ({"id": "X1", "buses": [_bus("X1/a", ch), _bus("X1/a", ch)]}, 422, "twice"),
            ({"id": "X1", "buses": [_bus("X1/a", ch, vehicle_id="X2")]}, 422, "not this vehicle"),
        ]
        for body, status, words in cases:
            r = await s.client.post(V, json=body, headers=s.auth())
            assert r.status_code == status and words in r.text, (body, r.text)
        r = await s.client.post(V, json={"id": "X1", "buses": [_bus("X1/a", ch)]},
                                headers=s.auth())  # fmt: skip
        assert r.status_code == 201, r.text
        r = await s.client.post(V, json={"id": "X2", "buses": [_bus("X1/a", ch)]},
                                headers=s.auth())  # fmt: skip
        assert r.status_code == 409 and "bus of another vehicle" in r.text, r.text
        viewer = await s.key("viewer")
        r = await s.client.post(V, json={"id": "X3"}, headers=s.auth(viewer))
        assert r.status_code == 403, r.text
        # Refused bodies audited as any invalid write is (by route), the others by action.
        refused = await _audit(s, "vehicle.create") + await _audit(s, "POST /vehicles")
        assert len([e for e in refused if e["outcome"] == "refused"]) >= len(cases)


GOOD = """\
vehicle_id,name,depot,bus,interface,channel,bitrate,equalizer_sas,options.host,options.port
BUS-101,Bus 101,north,BUS-101/can0,socketcand,can0,none,30 31,127.0.0.1,9
BUS-101,,,BUS-101/can1,socketcand,can1,none,30,127.0.0.1,9
BUS-102,Bus 102,north,,,,,,,
"""

BAD = """vehicle_id,name,depot,bus,interface,channel,equalizer_sas,gateway_sa,options
BUS-201,Bus 201,north,BUS-201/can0,socketcand,can0,30,,"{""host"": ""127.0.0.1"", ""port"": 9}"
BUS-202,,north,BUS-202/can0,nope,can0,30,,
BUS-203,,north,BUS-203/can0,virtual,c,300,,
BUS-204,,north,BUS-201/can0,virtual,c,30,,
BUS-205,,north,,virtual,,,,
BUS-206,,north,BUS-206/can0,virtual,c,30,x,
BUS-201,Other name,north,,,,,,
BUS/207,,north,,,,,,
BUS-208,,north,BUS-208/can0,virtual,c,30,,[1]
"""
BAD_LINES = {
    3: "is not a python-can interface",
    4: "source address 300 is not 0..253",
    5: "given twice (line 2)",
    6: "interface given without a bus name",
    7: "gateway_sa: 'x' is not a whole number",
    8: "differs from 'Bus 201' on line 2",
    9: "no '/'",
    10: "options: not a JSON object",
}


async def _fleet(s: Served) -> registry.Fleet:
    fleet: registry.Fleet = await s.rt.db(registry.load)
    return fleet


async def test_csv_import_dry_run_bad_rows_and_one_transaction(db_url: str) -> None:
    async with served(db_url, vehicles=1) as s:
        before = await _fleet(s)
        # Every bad row, with its line and reason; nothing applied (the good row neither).
        r = await s.client.post(f"{V}/import", content=BAD, headers={**s.auth(), **CSV})
        assert r.status_code == 422, r.text
        body = r.json()
        assert body["type"] == "invalid_rows" and body["applied"] is False
        got = {e["line"]: e["reason"] for e in body["bad_rows"]}
        assert set(got) == set(BAD_LINES), got
        for line, words in BAD_LINES.items():
            assert words in got[line], (line, got[line])
        after = await _fleet(s)
        assert after.version == before.version and "BUS-201" not in after.vehicles
        # A dry run lists what would change and changes nothing.
        r = await s.client.post(f"{V}/import", params={"dry_run": "true"}, content=GOOD,
                                headers={**s.auth(), **CSV})  # fmt: skip
        assert r.status_code == 200, r.text
        report = r.json()
        assert report["dry_run"] is True and report["applied"] is False
        assert [(c["id"], c["line"]) for c in report["added"]] == [("BUS-101", 2), ("BUS-102", 4)]
        assert report["added"][0]["buses_added"] == ["BUS-101/can0", "BUS-101/can1"]
        assert report["untouched"] == ["SIM-001"] and report["bad_rows"] == []
        assert (await _fleet(s)).version == before.version
        # Applied: both vehicles in one change, their buses opened (they back off: nothing
        # listens on port 9), one version step.
        r = await s.client.post(f"{V}/import", content=GOOD, headers={**s.auth(), **CSV})
        assert r.status_code == 200 and r.json()["applied"] is True, r.text
        fleet = await _fleet(s)
        assert fleet.version == before.version + 1
        assert fleet.vehicles["BUS-101"].depot == "north"
        assert fleet.buses["BUS-101/can0"].equalizer_sas == [30, 31]
        assert fleet.buses["BUS-101/can0"].options == {"host": "127.0.0.1", "port": 9}
        assert fleet.buses["BUS-101/can0"].bitrate is None
        assert {"BUS-101/can0", "BUS-101/can1"} <= set(s.rt.ingest.reading())
        # The same file again changes nothing; a changed one says what changes.
        r = await s.client.post(f"{V}/import", content=GOOD, headers={**s.auth(), **CSV})
        assert r.json()["applied"] is False and r.json()["unchanged"] == ["BUS-101", "BUS-102"]
        changed = GOOD.replace("Bus 102,north", "Bus 102,south").replace(
            "BUS-101,,,BUS-101/can1,socketcand,can1,none,30,127.0.0.1,9\n", ""
        )
        r = await s.client.post(f"{V}/import", params={"dry_run": True, "mode": "replace"},
                                content=changed, headers={**s.auth(), **CSV})  # fmt: skip
        report = r.json()
        assert report["changed"] == [
            {"id": "BUS-101", "line": 2, "fields": ["buses"], "buses_added": [],
             "buses_changed": [], "buses_removed": ["BUS-101/can1"]},
            {"id": "BUS-102", "line": 3, "fields": ["depot"], "buses_added": [],
             "buses_changed": [], "buses_removed": []},
        ]  # fmt: skip
        assert [c["id"] for c in report["removed"]] == ["SIM-001"]
        # Exported, the fleet reads back as it is.
        from eqgw.fleet import importer

        exported = importer.write(await _fleet(s))
        r = await s.client.post(f"{V}/import", content=exported, headers={**s.auth(), **CSV})
        assert r.status_code == 200 and not r.json()["applied"], r.text
        entries = await _audit(s, "vehicle.import")
        assert {e["vehicle_id"] for e in entries if e["outcome"] == "accepted"} >= {
            "BUS-101", "BUS-102",
        }  # fmt: skip
        assert any(e["outcome"] == "refused" for e in entries)
        as_json = {**s.auth(), "content-type": "application/json"}
        r = await s.client.post(f"{V}/import", content=GOOD, headers=as_json)
        assert r.status_code == 415


async def test_a_scoped_admin_manages_only_its_depots(db_url: str) -> None:
    async with served(db_url, config=_depots_config(), write_rate=1000) as s:
        r = await s.client.post("/api/v1/keys", headers=s.auth(), json={
            "name": "north admin", "role": "admin", "scope": {"groups": ["north"]}})  # fmt: skip
        north = s.auth(r.json()["key"])
        ch = s.sim.vehicles["SIM-001"].channel
        # Created in its depot: yes; in another: 403.
        r = await s.client.post(V, json={"id": "N-1", "depot": "north"}, headers=north)
        assert r.status_code == 201, r.text
        r = await s.client.post(V, json={"id": "S-1", "depot": "south"}, headers=north)
        assert r.status_code == 403 and r.json()["type"] == "out_of_scope", r.text
        r = await s.client.post(V, json={"id": "S-1"}, headers=north)  # no depot
        assert r.status_code == 403, r.text
        # Its new vehicle is in its scope at once (reads, commands' 404s and all).
        r = await s.client.get(f"{V}/N-1/config", headers=north)
        assert r.status_code == 200, r.text
        # Moved out of its depot: 403; another depot's vehicle: 404 as one that does not exist.
        r = await s.client.patch(f"{V}/N-1", json={"depot": "south"}, headers=north)
        assert r.status_code == 403, r.text
        for method, path, body in (
            ("PATCH", f"{V}/SIM-003", {"depot": "north"}),
            ("DELETE", f"{V}/SIM-003", None),
            ("GET", f"{V}/SIM-003/config", None),
        ):
            r = await s.client.request(method, path, json=body, headers=north)
            twin = await s.client.request(method, path.replace("SIM-003", "NOPE"), json=body,
                                          headers=north)  # fmt: skip
            assert r.status_code == twin.status_code == 404, (method, r.text)
            assert r.json()["detail"].replace("SIM-003", "NOPE") == twin.json()["detail"]
        # An import with one row of another depot: 403, that row named, nothing applied.
        text = (
            "vehicle_id,depot,bus,interface,channel,bitrate,address_claim\n"
            f"N-2,north,N-2/can0,virtual,{ch},none,false\n"
            "S-2,south,,,,,\n"
            "SIM-003,north,,,,,\n"
        )
        r = await s.client.post(f"{V}/import", content=text, headers={**north, **CSV})
        assert r.status_code == 403, r.text
        assert [(e["line"], e["reason"]) for e in r.json()["bad_rows"]] == [
            (3, "depot 'south' is outside this key's scope"),
            (4, "vehicle 'SIM-003' is outside this key's scope"),
        ]
        assert "N-2" not in (await _fleet(s)).vehicles
        # In replace mode, only its own depot's vehicles the file leaves out are removed.
        text = "vehicle_id,depot\nN-1,north\n"
        r = await s.client.post(f"{V}/import", params={"mode": "replace", "dry_run": True},
                                content=text, headers={**north, **CSV})  # fmt: skip
        assert r.status_code == 200, r.text
        assert sorted(c["id"] for c in r.json()["removed"]) == ["SIM-001", "SIM-002"]
        # The whole-fleet admin moves a vehicle into the north depot: the north admin has it.
        r = await s.client.patch(f"{V}/SIM-003", json={"depot": "north"}, headers=s.auth())
        assert r.status_code == 200, r.text
        r = await s.client.get(f"{V}/SIM-003/live", headers=north)
        assert r.status_code == 200, r.text
        refused = [e for e in await _audit(s, "vehicle.update") if e["outcome"] == "refused"]
        assert {e["status_code"] for e in refused} >= {403, 404}


def test_the_command_line_imports_and_exports(db_url: str, tmp_path: Path, capsys: Any) -> None:
    good = tmp_path / "fleet.csv"
    good.write_text(GOOD)
    bad = tmp_path / "bad.csv"
    bad.write_text(BAD)
    db = ["--db", db_url]
    assert eqgw_main(["vehicles", "import", str(bad), *db]) == 1
    err = capsys.readouterr().err
    for line, words in BAD_LINES.items():
        assert f"line {line}: " in err and words in err, (line, err)
    assert "nothing was changed" in err
    assert eqgw_main(["vehicles", "import", str(good), "--dry-run", *db]) == 0
    out = capsys.readouterr().out
    assert "added     BUS-101 (line 2): buses BUS-101/can0, BUS-101/can1" in out
    assert "dry run: nothing was changed" in out
    engine = create_engine(db_url)
    try:
        assert registry.load_fleet(engine).vehicles == {}
        assert eqgw_main(["vehicles", "import", str(good), *db]) == 0
        assert "fleet version 1" in capsys.readouterr().out
        fleet = registry.load_fleet(engine)
        assert set(fleet.vehicles) == {"BUS-101", "BUS-102"}
        with engine.connect() as conn:
            rows = conn.exec_driver_sql(
                "SELECT key_name, vehicle_id FROM audit_log WHERE action = 'vehicle.import'"
            ).all()
        assert {r[1] for r in rows} == {"BUS-101", "BUS-102", None}
        assert all("command line" in r[0] for r in rows)
    finally:
        engine.dispose()
    # The commands that read the fleet without serving it (replay, keys rotate) take the
    # database's once it has one.
    effective = registry.in_effect(Settings(database_url=db_url))
    assert [(b.name, b.equalizer_sas) for b in effective.buses] == [
        ("BUS-101/can0", [30, 31]),
        ("BUS-101/can1", [30]),
    ]
    assert eqgw_main(["vehicles", "export", *db]) == 0
    exported = capsys.readouterr().out
    assert exported.splitlines()[1].startswith("BUS-101,Bus 101,north,BUS-101/can0,socketcand")
    again = tmp_path / "again.csv"
    again.write_text(exported)
    assert eqgw_main(["vehicles", "import", str(again), *db]) == 0
    assert "nothing to change" in capsys.readouterr().out


async def test_the_fleet_file_seeds_an_empty_database_only(
    sqlite_url: str, caplog: pytest.LogCaptureFixture
) -> None:
    def settings(*vehicles: str) -> Settings:
        return Settings(
            database_url=sqlite_url,
            vehicles=[VehicleConfig(id=v, depot="north") for v in vehicles],
            buses=[
                BusConfig(
                    name=f"{v}/can0",
                    vehicle_id=v,
                    interface="virtual",
                    channel=f"seed-{v}",
                    bitrate=None,
                )
                for v in vehicles
            ],
        )

    async def run(s: Settings) -> tuple[list[str], list[str]]:
        app = create_app(s, api=ApiSettings())
        async with lifespan(app):
            rt = app.state.rt
            return sorted(v.id for v in rt.settings.vehicles), rt.ingest.reading()

    caplog.set_level(logging.INFO, logger="eqgw.fleet.lifespan")
    assert await run(settings("A", "B")) == (["A", "B"], ["A/can0", "B/can0"])
    assert "seeded from the fleet file (2 vehicles, 2 buses)" in caplog.text
    caplog.clear()
    # The same file again: nothing to say; another one: the database wins, and says so.
    assert await run(settings("A", "B")) == (["A", "B"], ["A/can0", "B/can0"])
    assert "not applied" not in caplog.text
    assert await run(settings("A", "C")) == (["A", "B"], ["A/can0", "B/can0"])
    assert "fleet file's vehicles and buses were not applied" in caplog.text
    assert "vehicle C, bus C/can0" in caplog.text


async def test_a_large_import_has_its_own_deadline(db_url: str) -> None:
    """An import is one transaction however many rows: it gets `import_deadline_s`, not the
    deadline of every other request (here far too short for it)."""
    rows = ["vehicle_id,name,depot"]  # vehicles only: opening 1000 buses is not the subject
    rows += [f"V{i:04d},Vehicle {i},D{i % 10}" for i in range(1000)]
    async with served(db_url, vehicles=1, db_deadline_s=0.05, import_deadline_s=60) as s:
        r = await s.client.post(f"{V}/import", content="\n".join(rows), headers={**s.auth(), **CSV})
        assert r.status_code == 200 and len(r.json()["added"]) == 1000, r.text[:300]
        assert len((await _fleet(s)).vehicles) == 1001


async def test_a_running_gateway_follows_an_import_made_elsewhere(
    db_url: str, tmp_path: Path
) -> None:
    """`eqgw vehicles import` writes the database directly: the running gateway learns of it
    by its poll of the fleet's version (the only way on SQLite), and opens the bus."""
    async with served(db_url, vehicles=1) as s:
        channel = s.sim.vehicles["SIM-001"].channel
        csv = tmp_path / "more.csv"
        csv.write_text(
            "vehicle_id,depot,bus,interface,channel,bitrate,address_claim\n"
            f"CLI-1,north,CLI-1/can0,virtual,{channel},none,false\n"
        )
        before = s.rt.fleet_sync.version
        code = await asyncio.to_thread(eqgw_main, ["vehicles", "import", str(csv), "--db", db_url])
        assert code == 0
        await wait_for(lambda: _units_on(s, "CLI-1/can0"), what="the imported bus read")
        assert s.rt.fleet_sync.version == before + 1
        listed = (await s.client.get(V, headers=s.auth())).json()["vehicles"]
        assert "CLI-1" in {v["id"] for v in listed}
