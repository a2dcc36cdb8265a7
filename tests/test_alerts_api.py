"""The alert endpoints: list, filter, acknowledge, rules, mutes; roles and bad input."""

from __future__ import annotations

import asyncio
import time
from typing import Any

from eqgw.ingest.events import ALERT_KINDS
from tests.api_helpers import Served, heap_frozen, served, wait_for

A = "/api/v1/alerts"


async def _alerts(s: Served, **params: Any) -> list[dict[str, Any]]:
    r = await s.client.get(A, params=params, headers=s.auth())
    assert r.status_code == 200, r.text
    alerts: list[dict[str, Any]] = r.json()["alerts"]
    return alerts


async def test_alert_lifecycle_acknowledge_and_roles(db_url: str) -> None:
    async with served(db_url, vehicles=2) as s:
        viewer, operator = await s.key("viewer"), await s.key("operator", "Ann")
        sub = s.rt.ingest.hub.subscribe(ALERT_KINDS)
        s.sim.fail_equalizer("SIM-001")

        async def raised() -> list[dict[str, Any]]:
            return await _alerts(s, vehicle="SIM-001", rule="equalizer_fault", state="open")

        (alert,) = await wait_for(raised, what="equalizer_fault alert")
        assert alert["state"] == "active" and alert["severity"] == "critical"
        assert alert["vehicle_name"] == "SIM-001" and alert["message"]
        alert_id = alert["id"]
        # Filters.
        assert [a["id"] for a in await _alerts(s, severity="critical,warning", state="active")]
        assert await _alerts(s, vehicle="SIM-002", rule="equalizer_fault") == []
        assert await _alerts(s, to="0") == []
        assert alert_id in [a["id"] for a in await _alerts(s, **{"from": "2020-01-01T00:00"})]
        for bad in ({"state": "open,bogus"}, {"severity": "loud"}, {"from": "yesterday"},
                    {"limit": "0"}):  # fmt: skip
            r = await s.client.get(A, params=bad, headers=s.auth(viewer))
            assert r.status_code == 422, (bad, r.text)
            assert r.json()["detail"]
        # Acknowledge: viewers may not, operators may, once.
        url = f"{A}/{alert_id}/acknowledge"
        r = await s.client.post(url, json={"comment": "x"}, headers=s.auth(viewer))
        assert r.status_code == 403 and "operator" in r.json()["detail"]
        r = await s.client.post(url, json={"comment": "x"})
        assert r.status_code == 401
        r = await s.client.post(url, json={"comment": 5}, headers=s.auth(operator))
        assert r.status_code == 422
        r = await s.client.post(url, json={"comment": "on my way"}, headers=s.auth(operator))
        assert r.status_code == 200, r.text
        acked = r.json()
        assert acked["state"] == "acknowledged" and acked["acknowledged_by"] == "Ann"
        assert acked["ack_comment"] == "on my way" and acked["acknowledged_at"] <= time.time()
        r = await s.client.post(url, json={}, headers=s.auth(operator))
        assert r.status_code == 409 and "acknowledged" in r.json()["detail"]
        r = await s.client.post(f"{A}/999999/acknowledge", json={}, headers=s.auth(operator))
        assert r.status_code == 404
        # The unit is repaired: the alert clears (acknowledged before, so not "cleared
        # without acknowledgement").
        s.sim.restore_equalizer("SIM-001")

        async def cleared() -> dict[str, Any] | None:
            r = await s.client.get(f"{A}/{alert_id}", headers=s.auth(viewer))
            body: dict[str, Any] = r.json()
            return body if body["state"] == "cleared" else None

        detail = await wait_for(cleared, what="alert cleared")
        assert detail["acknowledged_by"] == "Ann" and detail["cleared_by"] == "condition"
        assert [e["kind"] for e in detail["events"]] == ["raised", "acknowledged", "cleared"]
        last = detail["events"][-1]["payload"]
        assert last["event"] == "cleared" and last["alert"]["state"] == "cleared"
        assert last["alert"]["ack_comment"] == "on my way"
        # The hub (and so the websocket) saw the three changes: each is published once its
        # transaction has committed, so the last may follow the read above by a moment.
        kinds: list[str] = []
        async with asyncio.timeout(30):
            while len(kinds) < 3:
                ev = await sub.get()
                if ev.data["id"] == alert_id:
                    kinds.append(ev.kind)
        sub.close()
        assert kinds == ["alert_raised", "alert_acknowledged", "alert_cleared"]
        r = await s.client.get(f"{A}/999999", headers=s.auth(viewer))
        assert r.status_code == 404
        r = await s.client.get(f"{A}/abc", headers=s.auth(viewer))
        assert r.status_code == 422
        # Acknowledging a cleared alert is refused with the reason; refusals are audited.
        r = await s.client.post(url, json={}, headers=s.auth(operator))
        assert r.status_code == 409 and "cleared" in r.json()["detail"]
        r = await s.client.get("/api/v1/audit", headers=s.auth())
        actions = [(e["action"], e["outcome"]) for e in r.json()["entries"]]
        assert ("alert.acknowledge", "accepted") in actions
        assert ("alert.acknowledge", "refused") in actions


async def test_rules_crud_is_for_admins(db_url: str) -> None:
    async with served(db_url, vehicles=1) as s:
        viewer, operator = await s.key("viewer"), await s.key("operator")
        r = await s.client.get(f"{A}/rules", headers=s.auth(viewer))
        assert r.status_code == 200
        body = r.json()
        ids = {x["id"] for x in body["rules"]}
        assert ids == {
            "imbalance", "undervoltage", "overvoltage", "equalizer_fault", "offline",
            "heartbeat_stuck", "jump_start_left_on", "soc_low", "soh_low", "shutdown_risk",
            "not_reporting",
        }  # fmt: skip
        assert {x["source"] for x in body["rules"]} == {"builtin"}
        assert "imbalance" in body["kinds"] and "fire_v" in body["kinds"]["imbalance"]["params"]
        new = {
            "id": "ex24f",
            "kind": "fault",
            "severity": "warning",
            "params": {"fault": "EX24F", "delay_s": 5},
            "targets": ["depot-north"],
        }
        for key in (viewer, operator):
            r = await s.client.post(f"{A}/rules", json=new, headers=s.auth(key))
            assert r.status_code == 403
        r = await s.client.post(f"{A}/rules", json=new, headers=s.auth())
        assert r.status_code == 201, r.text
        assert r.json()["source"] == "api" and r.json()["targets"] == ["depot-north"]
        r = await s.client.post(f"{A}/rules", json=new, headers=s.auth())
        assert r.status_code == 409
        bad_bodies = [
            ({**new, "id": "x2", "kind": "nonsense"}, "kind"),
            ({**new, "id": "x3", "severity": "loud"}, "severity"),
            ({**new, "id": "Bad Id"}, "id"),
            ({**new, "id": "x4", "params": {}}, "fault"),
            ({**new, "id": "x5", "params": {"fault": "X", "delay_s": -1}}, "delay_s"),
            (
                {
                    "id": "x6",
                    "kind": "imbalance",
                    "severity": "info",
                    "params": {"fire_v": 0.2, "clear_v": 0.3},
                },
                "clear_v",
            ),
            ({**new, "id": "x7", "extra": 1}, "extra"),
        ]
        for bad, word in bad_bodies:
            r = await s.client.post(f"{A}/rules", json=bad, headers=s.auth())
            assert r.status_code == 422, (bad, r.text)
            assert word in r.json()["detail"], r.text
        # Change a built-in rule: params merge, the change is the API's now.
        r = await s.client.patch(
            f"{A}/rules/imbalance", json={"params": {"fire_v": 0.2}}, headers=s.auth()
        )
        assert r.status_code == 200, r.text
        rule = r.json()
        assert rule["params"]["fire_v"] == 0.2 and rule["params"]["clear_v"] == 0.07
        assert rule["source"] == "api"
        r = await s.client.patch(
            f"{A}/rules/imbalance", json={"params": {"clear_v": 0.5}}, headers=s.auth()
        )
        assert r.status_code == 422 and "hysteresis" in r.json()["detail"]
        r = await s.client.patch(f"{A}/rules/imbalance", json={"enabled": False},
                                 headers=s.auth(operator))  # fmt: skip
        assert r.status_code == 403
        r = await s.client.patch(f"{A}/rules/nope", json={"enabled": False}, headers=s.auth())
        assert r.status_code == 404
        r = await s.client.get(f"{A}/rules/imbalance", headers=s.auth(viewer))
        assert r.json()["params"]["fire_v"] == 0.2
        # Built-in rules are disabled, not deleted; the API's own are deleted.
        r = await s.client.delete(f"{A}/rules/imbalance", headers=s.auth())
        assert r.status_code == 409 and "disable" in r.json()["detail"]
        r = await s.client.delete(f"{A}/rules/ex24f", headers=s.auth(operator))
        assert r.status_code == 403
        r = await s.client.delete(f"{A}/rules/ex24f", headers=s.auth())
        assert r.status_code == 200
        r = await s.client.get(f"{A}/rules/ex24f", headers=s.auth())
        assert r.status_code == 404
        r = await s.client.delete(f"{A}/rules/ex24f", headers=s.auth())
        assert r.status_code == 404


async def test_disabling_a_rule_clears_its_alerts(db_url: str) -> None:
    async with served(db_url, vehicles=1) as s:
        s.sim.fail_equalizer("SIM-001")

        async def raised() -> list[dict[str, Any]]:
            return await _alerts(s, rule="equalizer_fault", state="active")

        (alert,) = await wait_for(raised, what="equalizer_fault alert")
        r = await s.client.patch(
            f"{A}/rules/equalizer_fault", json={"enabled": False}, headers=s.auth()
        )
        assert r.status_code == 200
        r = await s.client.get(f"{A}/{alert['id']}", headers=s.auth())
        assert r.json()["state"] == "cleared" and r.json()["cleared_by"] == "rule_disabled"
        r = await s.client.patch(
            f"{A}/rules/equalizer_fault", json={"enabled": True}, headers=s.auth()
        )
        # Enabled again while the fault lasts: a new alert.
        (again,) = await wait_for(raised, what="a new equalizer_fault alert")
        assert again["id"] != alert["id"]


async def test_mutes(db_url: str) -> None:
    async with served(db_url, vehicles=2) as s:
        viewer, operator = await s.key("viewer"), await s.key("operator")
        mute = {"vehicle_id": "SIM-001", "rule": "equalizer_fault", "duration_s": 3600,
                "reason": "in the workshop"}  # fmt: skip
        for key in (viewer, operator):
            r = await s.client.post(f"{A}/mutes", json=mute, headers=s.auth(key))
            assert r.status_code == 403
        now = time.time()
        bad_bodies = [
            ({"duration_s": 60, "ends_at": now + 60}, 422, "exactly one"),
            ({"vehicle_id": "SIM-001"}, 422, "exactly one"),
            ({"ends_at": now - 10}, 422, "future"),
            ({"duration_s": 400 * 86400}, 422, "duration_s"),
            ({"duration_s": 60, "vehicle_id": "NOPE"}, 404, "NOPE"),
            ({"duration_s": 60, "rule": "nope"}, 404, "nope"),
            ({"duration_s": 60, "quiet_hours": {"from": "25:00", "to": "06:00"}}, 422, "from"),
            ({"duration_s": 60, "quiet_hours": {"from": "06:00", "to": "06:00"}}, 422, "window"),
        ]
        for bad, status, word in bad_bodies:
            r = await s.client.post(f"{A}/mutes", json=bad, headers=s.auth())
            assert r.status_code == status, (bad, r.text)
            assert word in r.json()["detail"], r.text
        r = await s.client.post(f"{A}/mutes", json=mute, headers=s.auth())
        assert r.status_code == 201, r.text
        created = r.json()
        assert created["active"] and created["ends_at"] > now + 3000
        assert created["quiet_hours"] is None and created["created_by"] == "first admin"
        # A fleet-wide mute whose daily window (UTC) is not now: it mutes nothing yet. The
        # window is placed 2-4 h from the clock, so the test holds at any hour it runs.
        hhmm = [time.strftime("%H:%M", time.gmtime(now + h * 3600)) for h in (2, 4)]
        window = {"from": hhmm[0], "to": hhmm[1]}
        r = await s.client.post(
            f"{A}/mutes", json={"duration_s": 86400, "quiet_hours": window}, headers=s.auth()
        )
        assert r.status_code == 201 and r.json()["quiet_hours"] == window
        r = await s.client.get(f"{A}/mutes", params={"active": "true"}, headers=s.auth(viewer))
        assert created["id"] in [m["id"] for m in r.json()["mutes"]]
        # A muted alert is recorded, marked muted; its events are marked for the delivery.
        s.sim.fail_equalizer("SIM-001")
        s.sim.fail_equalizer("SIM-002")

        async def both() -> list[dict[str, Any]]:
            found = await _alerts(s, rule="equalizer_fault")
            return found if len(found) == 2 else []

        alerts = {a["vehicle_id"]: a for a in await wait_for(both, what="two alerts")}
        assert alerts["SIM-001"]["muted"] and not alerts["SIM-002"]["muted"]
        assert [a["id"] for a in await _alerts(s, muted="true")] == [alerts["SIM-001"]["id"]]
        r = await s.client.get(f"{A}/{alerts['SIM-001']['id']}", headers=s.auth())
        assert all(e["muted"] for e in r.json()["events"])
        # Ending the mute.
        r = await s.client.delete(f"{A}/mutes/{created['id']}", headers=s.auth(operator))
        assert r.status_code == 403
        r = await s.client.delete(f"{A}/mutes/{created['id']}", headers=s.auth())
        assert r.status_code == 200 and not r.json()["active"] and r.json()["cancelled_at"]
        r = await s.client.delete(f"{A}/mutes/{created['id']}", headers=s.auth())
        assert r.status_code == 404
        r = await s.client.get(f"{A}/mutes", params={"active": "true"}, headers=s.auth())
        assert created["id"] not in [m["id"] for m in r.json()["mutes"]]


def test_the_websocket_forwards_alert_events(sqlite_url: str) -> None:
    import warnings

    from eqgw.config import Settings
    from eqgw.main import create_app
    from eqgw.sim.clock import RealtimeClock
    from eqgw.sim.fleet import SimulatedFleet
    from eqgw.web.settings import ApiSettings
    from tests.test_api_ws import _recv, _until

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # Starlette asks for httpx2; httpx works
        from starlette.testclient import TestClient

    keys: list[str] = []
    sim = SimulatedFleet(2, seed=1, clock=RealtimeClock(4.0))
    app = create_app(
        Settings(database_url=sqlite_url), api=ApiSettings(), sim=sim, on_first_key=keys.append
    )
    with heap_frozen(), TestClient(app) as client:
        deadline = time.monotonic() + 60
        while len(app.state.rt.ingest.live.units) < 2:
            assert time.monotonic() < deadline
            time.sleep(0.05)
        with client.websocket_connect(f"/api/v1/ws?key={keys[0]}&vehicles=SIM-002") as ws:
            assert _recv(ws)["type"] == "snapshot"
            client.portal.call(sim.fail_equalizer, "SIM-001")  # not subscribed: never sent
            client.portal.call(sim.fail_equalizer, "SIM-002")
            msgs = _until(
                ws,
                lambda m: m["type"] == "alert_raised" and m["data"]["rule"] == "equalizer_fault",
                timeout=30,
            )
            assert {m["vehicle_id"] for m in msgs} == {"SIM-002"}
            msg = msgs[-1]
            alert = msg["data"]
            assert alert["state"] == "active" and msg["unit"] == alert["sa"]
            r = client.post(
                f"{A}/{alert['id']}/acknowledge",
                json={"comment": "seen"},
                headers={"Authorization": f"Bearer {keys[0]}"},
            )
            assert r.status_code == 200
            msg = _until(ws, lambda m: m["type"] == "alert_acknowledged", timeout=30)[-1]
            assert msg["data"]["id"] == alert["id"] and msg["data"]["ack_comment"] == "seen"
