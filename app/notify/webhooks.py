"""Webhook bodies (JSON and Slack), their signature (Standard Webhooks), and one HTTP attempt.

A body is the alert event as the alert engine wrote it, plus `event_id` and `links`. It is signed
as Standard Webhooks (standardwebhooks.com) specifies: `webhook-id` (the event id, the same on
every retry), `webhook-timestamp` (epoch seconds) and `webhook-signature` (`v1,` and the base64
HMAC-SHA256 of `id.timestamp.body`), so a receiver verifies with a standardwebhooks library in
any language, refuses a timestamp outside its replay window and dedupes on the id.

The HMAC key of a secret: `whsec_` and base64 (the form eqgw generates) is the decoded bytes
(the standard or the URL-safe alphabet, padding optional); any other text is its UTF-8 bytes
(a library's "raw" secret).
"""

from __future__ import annotations

import base64
import binascii
import hashlib
import hmac
import secrets
import time
from collections.abc import Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import orjson

if TYPE_CHECKING:
    import httpx

# Standard Webhooks.
ID_HEADER = "webhook-id"
TIMESTAMP_HEADER = "webhook-timestamp"
SIGNATURE_HEADER = "webhook-signature"
# eqgw's own: what the event is, and which delivery (log line) this attempt belongs to.
EVENT_ID_HEADER = "X-Eqgw-Event-Id"
EVENT_HEADER = "X-Eqgw-Event"
DELIVERY_HEADER = "X-Eqgw-Delivery"
# The signature of earlier versions (hex HMAC-SHA256 of `timestamp.body` keyed with the secret's
# text), still sent so receivers written for it keep working; deprecated.
LEGACY_TIMESTAMP_HEADER = "X-Eqgw-Timestamp"
LEGACY_SIGNATURE_HEADER = "X-Eqgw-Signature"
USER_AGENT = "eqgw-webhook/0.1"
REPLAY_WINDOW_S = 300
SECRET_PREFIX = "whsec_"
FORMATS = ("json", "slack")

_SEVERITY_ICON = {
    "critical": ":red_circle:",
    "warning": ":large_orange_circle:",
    "info": ":large_blue_circle:",
}
_KIND_VERB = {
    "raised": "raised",
    "acknowledged": "acknowledged",
    "cleared": "cleared",
    "test": "test",
}


def new_secret() -> str:
    """A random signing secret: `whsec_` and the standard base64 of 32 random bytes."""
    return SECRET_PREFIX + base64.b64encode(secrets.token_bytes(32)).decode()


class SecretError(ValueError):
    """A `whsec_` secret whose rest is not base64."""


def signing_key(secret: str) -> bytes:
    """The HMAC key of a secret (see the module's docstring)."""
    if not secret.startswith(SECRET_PREFIX):
        return secret.encode()
    text = secret[len(SECRET_PREFIX) :].translate(str.maketrans("-_", "+/")).rstrip("=")
    try:
        key = base64.b64decode(text + "=" * (-len(text) % 4), validate=True)
    except (binascii.Error, ValueError) as exc:
        raise SecretError(f"a {SECRET_PREFIX} secret is base64 after the prefix") from exc
    if len(key) < 16:
        raise SecretError(f"a {SECRET_PREFIX} secret holds at least 16 bytes")
    return key


def links(alert: Mapping[str, Any], public_url: str) -> dict[str, str]:
    """Where a person looks at the vehicle (dashboard) and the alert (API)."""
    base = public_url.rstrip("/")
    return {
        "vehicle": f"{base}/#/vehicle/{alert.get('vehicle_id', '')}",
        "alert": f"{base}/api/v1/alerts/{alert.get('id', '')}",
    }


def event_body(payload: Mapping[str, Any], event_id: int | str, public_url: str) -> dict[str, Any]:
    """The JSON body of an alert event: the stored event plus its id and links."""
    alert = payload.get("alert") or {}
    return {**payload, "event_id": event_id, "links": links(alert, public_url)}


def test_payload(now: float | None = None) -> dict[str, Any]:
    """A made-up event for the "send test" action (its id starts with `test-`)."""
    ts = time.time() if now is None else now
    return {
        "event": "test",
        "ts": ts,
        "alert": {
            "id": 0,
            "vehicle_id": "TEST",
            "vehicle_name": "Test vehicle",
            "bus": "TEST/can0",
            "sa": 30,
            "rule": "test",
            "severity": "info",
            "state": "active",
            "message": "Test event from eqgw: this webhook is reachable and its secret works",
            "values": {},
            "raised_at": ts,
            "acknowledged_at": None,
            "acknowledged_by": None,
            "ack_comment": None,
            "cleared_at": None,
        },
    }


def slack_body(body: Mapping[str, Any]) -> dict[str, Any]:
    """A Slack-compatible incoming-webhook message (`text` plus blocks) for an event body."""
    alert = body.get("alert") or {}
    event = str(body.get("event", ""))
    severity = str(alert.get("severity", ""))
    vehicle = alert.get("vehicle_name") or alert.get("vehicle_id", "?")
    title = (
        f"{_SEVERITY_ICON.get(severity, ':white_circle:')} {severity.upper()} "
        f"{alert.get('rule', '?')} {_KIND_VERB.get(event, event)} on {vehicle}"
    )
    values = alert.get("values") or {}
    detail = ", ".join(f"{k} {v}" for k, v in values.items())
    text = f"{title}: {alert.get('message', '')}"
    who = ""
    if event == "acknowledged" and alert.get("acknowledged_by"):
        who = f"\nAcknowledged by {alert['acknowledged_by']}"
        if alert.get("ack_comment"):
            who += f": {alert['ack_comment']}"
    link = body.get("links") or {}
    blocks: list[dict[str, Any]] = [
        {
            "type": "section",
            "text": {"type": "mrkdwn", "text": f"*{title}*\n{alert.get('message', '')}{who}"},
        },
        {
            "type": "context",
            "elements": [
                {
                    "type": "mrkdwn",
                    "text": " | ".join(
                        p
                        for p in (
                            f"unit {alert.get('bus', '?')} SA {alert.get('sa', '?')}",
                            detail,
                            f"<{link['vehicle']}|vehicle>" if link.get("vehicle") else "",
                            f"<{link['alert']}|alert>" if link.get("alert") else "",
                            f"event {body.get('event_id', '')}",
                        )
                        if p
                    ),
                }
            ],
        },
    ]
    return {"text": text, "blocks": blocks}


def signature(secret: str, msg_id: str, timestamp: str, body: bytes) -> str:
    """The `webhook-signature` value: `v1,` and the base64 HMAC-SHA256 of `id.timestamp.body`."""
    signed = f"{msg_id}.{timestamp}.".encode() + body
    mac = hmac.new(signing_key(secret), signed, hashlib.sha256)
    return "v1," + base64.b64encode(mac.digest()).decode()


def legacy_signature(secret: str, timestamp: str, body: bytes) -> str:
    """The deprecated `X-Eqgw-Signature` value: `sha256=` and the hex HMAC of `timestamp.body`."""
    mac = hmac.new(secret.encode(), timestamp.encode() + b"." + body, hashlib.sha256)
    return "sha256=" + mac.hexdigest()


def verify(
    secret: str,
    headers: Mapping[str, str],
    body: bytes,
    *,
    now: float | None = None,
    window_s: float = REPLAY_WINDOW_S,
) -> bool:
    """What a receiver checks: a good signature over a timestamp inside the replay window
    (Standard Webhooks: any of the space-separated `v1,` signatures may match)."""
    lower = {k.lower(): v for k, v in headers.items()}
    msg_id = lower.get(ID_HEADER, "")
    ts = lower.get(TIMESTAMP_HEADER, "")
    if not msg_id or not ts.isdigit():
        return False
    if abs((time.time() if now is None else now) - int(ts)) > window_s:
        return False
    expected = signature(secret, msg_id, ts, body)
    return any(hmac.compare_digest(expected, s) for s in lower.get(SIGNATURE_HEADER, "").split())


def render(
    fmt: str, body: Mapping[str, Any], secret: str, *, delivery_id: int, now: float
) -> tuple[bytes, dict[str, str]]:
    """The bytes to POST and their headers (signed at each attempt, so retries stay fresh)."""
    content = orjson.dumps(slack_body(body) if fmt == "slack" else body)
    ts = str(int(now))
    msg_id = str(body.get("event_id", ""))
    headers = {
        "Content-Type": "application/json",
        "User-Agent": USER_AGENT,
        ID_HEADER: msg_id,
        TIMESTAMP_HEADER: ts,
        SIGNATURE_HEADER: signature(secret, msg_id, ts, content),
        EVENT_ID_HEADER: msg_id,
        EVENT_HEADER: str(body.get("event", "")),
        DELIVERY_HEADER: str(delivery_id),
        LEGACY_TIMESTAMP_HEADER: ts,
        LEGACY_SIGNATURE_HEADER: legacy_signature(secret, ts, content),
    }
    return content, headers


@dataclass(frozen=True, slots=True)
class Attempt:
    """The outcome of one POST: delivered on a 2xx, else the status or the error."""

    delivered: bool
    status: int | None
    error: str | None
    duration_s: float


async def post(
    client: httpx.AsyncClient, url: str, content: bytes, headers: Mapping[str, str], timeout: float
) -> Attempt:
    """POST once; never raises for network trouble (it is the attempt's outcome)."""
    start = time.monotonic()
    try:
        resp = await client.post(url, content=content, headers=dict(headers), timeout=timeout)
    except Exception as exc:  # any failure to get a response is this attempt's outcome
        reason = str(exc) or type(exc).__name__
        return Attempt(False, None, f"{type(exc).__name__}: {reason}", time.monotonic() - start)
    elapsed = time.monotonic() - start
    if 200 <= resp.status_code < 300:
        return Attempt(True, resp.status_code, None, elapsed)
    # The status alone: a receiver's body is never kept nor shown (a webhook pointed at an
    # internal page must not bring that page back to whoever reads the delivery log).
    return Attempt(
        False, resp.status_code, f"HTTP {resp.status_code} {resp.reason_phrase}".strip(), elapsed
    )
