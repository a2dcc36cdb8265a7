"""The webhook API (admin only, audited) on the running app, and delivery through its lifespan."""

from __future__ import annotations

from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from typing import Any

import httpx
from fastapi import FastAPI

from eqgw.config import DeliverySettings, Settings
from eqgw.main import create_app
from eqgw.web.settings import ApiSettings
from tests.api_helpers import lifespan, wait_for
from tests.webhook_helpers import ALLOW_LOOPBACK, Receiver, add_alert, add_event

W = "/api/v1/webhooks"


@asynccontextmanager
async def running(db_url: str) -> AsyncIterator[tuple[FastAPI, httpx.AsyncClient, dict[str, str]]]:
    """The app without buses, with fast delivery settings, an admin key and a client."""
    keys: list[str] = []
    delivery = DeliverySettings(poll_s=0.05, retry_initial_s=0.1, retry_max_s=0.4, timeout_s=5)
    app = create_app(
        Settings(database_url=db_url, delivery=delivery, webhook_allow_networks=ALLOW_LOOPBACK),
        api=ApiSettings(public_url="http://depot.example"),
        on_first_key=keys.append,
    )
    async with lifespan(app):
        transport = httpx.ASGITransport(app=app)
        async with httpx.AsyncClient(transport=transport, base_url="http://test") as client:
            yield app, client, {"Authorization": f"Bearer {keys[0]}"}


async def test_webhook_crud_test_action_log_and_roles(db_url: str) -> None:
    receiver = Receiver("placeholder").start()
    try:
        async with running(db_url) as (app, client, admin):
            bad = await client.post(W, json={"name": "x", "url": "ftp://h/x"}, headers=admin)
            assert bad.status_code == 422 and "http" in bad.text
            short = await client.post(
                W, json={"name": "x", "url": receiver.url, "secret": "short"}, headers=admin
            )
            assert short.status_code == 422
            r = await client.post(W, json={"name": "ops", "url": receiver.url}, headers=admin)
            assert r.status_code == 201, r.text
            hook = r.json()
            assert hook["secret"].startswith("whsec_") and hook["format"] == "json"
            receiver.secret = hook["secret"]
            dup = await client.post(W, json={"name": "ops", "url": receiver.url}, headers=admin)
            assert dup.status_code == 409
            listed = (await client.get(W, headers=admin)).json()
            assert [h["name"] for h in listed] == ["ops"] and "secret" not in listed[0]
            one = (await client.get(f"{W}/{hook['id']}", headers=admin)).json()
            assert "secret" not in one and one["deliveries"]["pending"] == 0

            # Send test: signed, reported, logged.
            t = await client.post(f"{W}/{hook['id']}/test", headers=admin)
            assert t.status_code == 200, t.text
            assert t.json()["delivered"] is True and t.json()["status"] == 200
            assert receiver.bad_signatures == 0
            sent = receiver.accepted()[-1]
            assert sent["event"] == "test" and sent["event_id"].startswith("test-")

            # Rotating the secret: the old one no longer verifies.
            p = await client.patch(
                f"{W}/{hook['id']}", json={"rotate_secret": True, "format": "slack"}, headers=admin
            )
            assert p.status_code == 200 and p.json()["secret"] != hook["secret"]
            t = await client.post(f"{W}/{hook['id']}/test", headers=admin)
            assert t.json()["delivered"] is False and t.json()["status"] == 401
            receiver.secret = p.json()["secret"]
            t = await client.post(f"{W}/{hook['id']}/test", headers=admin)
            assert t.json()["delivered"] is True
            assert set(receiver.accepted()[-1]) == {"text", "blocks"}

            # An alert event written to the outbox reaches the receiver through the lifespan.
            await client.patch(f"{W}/{hook['id']}", json={"format": "json"}, headers=admin)
            engine = app.state.rt.engine
            alert = add_alert(engine)
            event_id = add_event(engine, alert, "raised")

            async def arrived() -> Any:
                return [b for b in receiver.accepted() if b.get("event_id") == event_id]

            body = (await wait_for(arrived, what="the alert event"))[0]
            assert body["links"] == {
                "vehicle": "http://depot.example/#/vehicle/BUS-1",
                "alert": f"http://depot.example/api/v1/alerts/{alert['id']}",
            }

            async def logged() -> Any:
                r = await client.get(f"{W}/{hook['id']}/deliveries", headers=admin)
                rows = r.json()["deliveries"]
                return [d for d in rows if d["event_id"] == event_id and d["state"] == "delivered"]

            await wait_for(logged, what="the delivery logged")
            log = (await client.get(f"{W}/{hook['id']}/deliveries", headers=admin)).json()
            kinds = [d["kind"] for d in log["deliveries"]]
            assert kinds.count("test") == 3 and "raised" in kinds
            failed = await client.get(
                f"{W}/{hook['id']}/deliveries", params={"state": "failed"}, headers=admin
            )
            assert [d["last_status"] for d in failed.json()["deliveries"]] == [401]

            # Roles: a viewer or operator reads nothing here and changes nothing.
            for role in ("viewer", "operator"):
                k = await client.post(
                    "/api/v1/keys", json={"name": role, "role": role}, headers=admin
                )
                other = {"Authorization": f"Bearer {k.json()['key']}"}
                assert (await client.get(W, headers=other)).status_code == 403
                denied = await client.post(
                    W, json={"name": "z", "url": receiver.url}, headers=other
                )
                assert denied.status_code == 403
            assert (await client.get(W)).status_code == 401

            gone = await client.delete(f"{W}/{hook['id']}", headers=admin)
            assert gone.status_code == 200
            assert (await client.get(f"{W}/{hook['id']}", headers=admin)).status_code == 404
            assert (await client.post(f"{W}/{hook['id']}/test", headers=admin)).status_code == 404

            audit = (await client.get("/api/v1/audit", headers=admin)).json()["entries"]
            actions = {(e["action"], e["outcome"]) for e in audit}
            assert {("webhook.create", "accepted"), ("webhook.create", "refused"),
                    ("webhook.update", "accepted"), ("webhook.test", "done"),
                    ("webhook.delete", "accepted")} <= actions  # fmt: skip
            assert not any("whsec_" in str(e["request"]) for e in audit)
            metrics = (await client.get("/metrics", headers=admin)).text
            assert "eqgw_webhook_attempts_total" in metrics
    finally:
        receiver.stop()


async def test_end_to_end_an_equalizer_fault_reaches_the_webhook(sqlite_url: str) -> None:
    """The simulator fails an equalizer, the alert engine raises `equalizer_fault`, the webhook
    receives it signed (the whole chain, with the rule engine of the alerting work)."""
    from tests.api_helpers import served

    receiver = Receiver("placeholder").start()
    try:
        config = {"webhook_allow_networks": ALLOW_LOOPBACK}
        async with served(sqlite_url, vehicles=1, config=config) as s:
            r = await s.client.post(
                W,
                json={"name": "faults", "url": receiver.url, "rules": ["equalizer_fault"]},
                headers=s.auth(),
            )
            assert r.status_code == 201, r.text
            receiver.secret = r.json()["secret"]
            s.sim.fail_equalizer("SIM-001")

            async def raised() -> Any:
                return [b for b in receiver.accepted() if b.get("event") == "raised"]

            body = (await wait_for(raised, timeout=90, what="the raised alert"))[0]
            assert body["alert"]["rule"] == "equalizer_fault"
            assert body["alert"]["vehicle_id"] == "SIM-001"
            assert body["alert"]["severity"] == "critical"
            assert body["links"]["vehicle"].endswith("/#/vehicle/SIM-001")
            assert receiver.bad_signatures == 0
    finally:
        receiver.stop()


BAD_PORTS = ("http://hooks.example:/hook", "https://hooks.example:/", "http://[2001:db8::1]:/x",
             "http://hooks.example:0/hook", "http://hooks.example:65536/hook",
             "http://hooks.example:http/hook", "http://u:p@hooks.example:/hook")  # fmt: skip


async def test_a_webhook_url_with_an_empty_or_bad_port_is_refused(db_url: str) -> None:
    """`http://host:/hook` was taken as port 80; an empty, zero, too large or non-numeric port
    is a 422 saying so, at creation and at a change, and nothing is stored."""
    async with running(db_url) as (_app, client, admin):
        for url in BAD_PORTS:
            r = await client.post(W, json={"name": "x", "url": url}, headers=admin)
            assert r.status_code == 422, (url, r.text)
            assert "port" in r.json()["detail"], r.text
        assert (await client.get(W, headers=admin)).json() == []
        r = await client.post(
            W, json={"name": "ok", "url": "http://127.0.0.1:8080/hook"}, headers=admin
        )
        assert r.status_code == 201, r.text
        hook = r.json()["id"]
        for url in BAD_PORTS[:2]:
            r = await client.patch(f"{W}/{hook}", json={"url": url}, headers=admin)
            assert r.status_code == 422 and "port" in r.json()["detail"], (url, r.text)
        assert (await client.get(f"{W}/{hook}", headers=admin)).json()["url"].endswith(":8080/hook")
