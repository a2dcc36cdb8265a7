"""Webhook signatures as Standard Webhooks: a receiver verifies with the standardwebhooks library.

Real deliveries and test sends go through the running app to a real HTTP receiver; the library,
not eqgw's own code, checks every request it got.
"""

from __future__ import annotations

import base64
import secrets
import time
from typing import Any

import pytest
from standardwebhooks import Webhook, WebhookVerificationError

from eqgw.notify.webhooks import SecretError, render, signing_key
from tests.api_helpers import wait_for
from tests.test_webhooks_api import W, running
from tests.webhook_helpers import Receiver, add_alert, add_event

# Headers every delivery carries, a test send as much as an alert event.
HEADERS = {
    "webhook-id",
    "webhook-timestamp",
    "webhook-signature",
    "x-eqgw-event",
    "x-eqgw-event-id",
    "x-eqgw-delivery",
}


def _lower(headers: dict[str, str]) -> dict[str, str]:
    return {k.lower(): v for k, v in headers.items()}


async def test_deliveries_and_test_sends_verify_with_the_standardwebhooks_library(
    db_url: str,
) -> None:
    receiver = Receiver("placeholder").start()
    try:
        async with running(db_url) as (app, client, admin):
            r = await client.post(W, json={"name": "ops", "url": receiver.url}, headers=admin)
            assert r.status_code == 201, r.text
            hook = r.json()
            receiver.secret = hook["secret"]
            library = Webhook(hook["secret"])

            t = await client.post(f"{W}/{hook['id']}/test", headers=admin)
            assert t.status_code == 200 and t.json()["delivered"] is True, t.text
            test_request = receiver.requests[-1]

            engine = app.state.rt.engine
            event_id = add_event(engine, add_alert(engine), "raised")

            async def arrived() -> Any:
                return [q for q in receiver.requests if q.json.get("event_id") == event_id]

            event_request = (await wait_for(arrived, what="the alert event"))[0]

            for request in (test_request, event_request):
                headers = _lower(request.headers)
                assert HEADERS <= set(headers), headers
                # The library raises on a bad signature, a missing header or an old timestamp.
                assert library.verify(request.body, headers) == request.json
                assert headers["webhook-id"] == str(request.json["event_id"])
                with pytest.raises(WebhookVerificationError):
                    library.verify(request.body + b" ", headers)
            # The test send names its delivery (log line) like any delivery does.
            assert _lower(test_request.headers)["x-eqgw-delivery"] == str(t.json()["delivery_id"])
            log = (await client.get(f"{W}/{hook['id']}/deliveries", headers=admin)).json()
            tests = [d for d in log["deliveries"] if d["kind"] == "test"]
            assert [(d["id"], d["state"], d["attempts"]) for d in tests] == [
                (t.json()["delivery_id"], "delivered", 1)
            ]
    finally:
        receiver.stop()


def test_secret_forms_and_their_keys() -> None:
    body = {"event": "raised", "event_id": 5}
    raw = "my-own-shared-secret"
    urlsafe = "whsec_" + secrets.token_urlsafe(32)  # what earlier versions generated
    for secret, library_secret in (
        ("whsec_" + base64.b64encode(b"k" * 32).decode(), None),
        (raw, raw.encode()),  # any other text: its UTF-8 bytes (a "raw" key)
        # Re-encoded for the library: the standard alphabet after the prefix.
        (urlsafe, "whsec_" + urlsafe[6:].translate(str.maketrans("-_", "+/"))),
    ):
        content, headers = render("json", body, secret, delivery_id=1, now=time.time())
        assert Webhook(library_secret or secret).verify(content, headers) == body
    assert signing_key("whsec_" + base64.b64encode(b"k" * 32).decode()) == b"k" * 32
    for bad in ("whsec_not*base64*at*all!", "whsec_" + base64.b64encode(b"short").decode()):
        with pytest.raises(SecretError):
            signing_key(bad)


async def test_a_whsec_secret_that_is_not_base64_is_refused(sqlite_url: str) -> None:
    async with running(sqlite_url) as (_app, client, admin):
        r = await client.post(
            W,
            json={"name": "x", "url": "http://127.0.0.1:9/x", "secret": "whsec_!!!!!!!!!!!!!!!!"},
            headers=admin,
        )
        assert r.status_code == 422 and "base64" in r.text, r.text
