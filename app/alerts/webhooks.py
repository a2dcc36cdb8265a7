"""Webhook bodies (JSON and Slack), their HMAC-SHA256 signature, and one HTTP attempt.

A body is the alert event as the alert engine wrote it, plus `event_id` and `links`. It is signed
over `f"{timestamp}.{body}"` with the webhook's secret; receivers check the signature, refuse a
timestamp outside their replay window and dedupe on the event id (a retry after a lost response
sends the same event again).
"""

from __future__ import annotations

import hashlib
import hmac
import secrets
import time
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import httpx
import orjson

EVENT_ID_HEADER = "X-Eqgw-Event-Id"
EVENT_HEADER = "X-Eqgw-Event"
TIMESTAMP_HEADER = "X-Eqgw-Timestamp"
SIGNATURE_HEADER = "X-Eqgw-Signature"
DELIVERY_HEADER = "X-Eqgw-Delivery"
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
    """A random signing secret (256 bits)."""
    return SECRET_PREFIX + secrets.token_urlsafe(32)


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


def signature(secret: str, timestamp: str, body: bytes) -> str:
    """The `X-Eqgw-Signature` value: `sha256=` and the hex HMAC of `timestamp.body`."""
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
    """What a receiver checks: a good signature over a timestamp inside the replay window."""
    lower = {k.lower(): v for k, v in headers.items()}
    ts = lower.get(TIMESTAMP_HEADER.lower(), "")
    sig = lower.get(SIGNATURE_HEADER.lower(), "")
    if not ts.isdigit():
        return False
    if abs((time.time() if now is None else now) - int(ts)) > window_s:
        return False
    return hmac.compare_digest(signature(secret, ts, body), sig)


def render(
    fmt: str, body: Mapping[str, Any], secret: str, *, delivery_id: int | None, now: float
) -> tuple[bytes, dict[str, str]]:
    """The bytes to POST and their headers (signed at each attempt, so retries stay fresh)."""
    content = orjson.dumps(slack_body(body) if fmt == "slack" else body)
    ts = str(int(now))
    headers = {
        "Content-Type": "application/json",
        "User-Agent": USER_AGENT,
        EVENT_ID_HEADER: str(body.get("event_id", "")),
        EVENT_HEADER: str(body.get("event", "")),
        TIMESTAMP_HEADER: ts,
        SIGNATURE_HEADER: signature(secret, ts, content),
    }
    if delivery_id is not None:
        headers[DELIVERY_HEADER] = str(delivery_id)
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
    text = resp.text[:200].strip()
    return Attempt(False, resp.status_code, f"HTTP {resp.status_code}: {text}", elapsed)
