"""One attempt to hand an alert event to a destination, by the destination's format.

Every destination is a row of `webhooks` and every event a row of its outbox
(`webhook_deliveries`): the dispatcher queues, claims, retries and gives up the same way for
each, and only the last step differs, `send`:

- `json`, `slack`: a signed POST (webhooks.py);
- `teams`: a POST of a message with an Adaptive Card, what a Microsoft Teams incoming webhook or
  a Workflows "post to a channel when a webhook request is received" URL takes;
- `pagerduty`: a PagerDuty Events API v2 event (the URL: `https://events.pagerduty.com/v2/enqueue`
  or a proxy's), the webhook's secret as the routing key, `dedup_key` `eqgw-alert-<alert id>`,
  and raised/acknowledged/cleared as trigger/acknowledge/resolve;
- `email`: a plain-text message to the `mailto:` URL's addresses through the SMTP server of
  the `smtp` settings (STARTTLS, implicit TLS or, for a local relay, none).
"""

from __future__ import annotations

import asyncio
import os
import secrets
import smtplib
import ssl
import time
from collections.abc import Mapping
from email.message import EmailMessage
from email.utils import formatdate
from typing import TYPE_CHECKING, Any
from urllib.parse import unquote

import orjson

from eqgw.notify.webhooks import (
    DELIVERY_HEADER,
    EVENT_HEADER,
    EVENT_ID_HEADER,
    USER_AGENT,
    Attempt,
    post,
    render,
)

if TYPE_CHECKING:
    import httpx

    from eqgw.config import SmtpSettings

FORMATS = ("json", "slack", "teams", "pagerduty", "email")
MAX_RECIPIENTS = 20
_VERB = {"raised": "raised", "acknowledged": "acknowledged", "cleared": "cleared", "test": "test"}
_PD_ACTION = {"raised": "trigger", "acknowledged": "acknowledge", "cleared": "resolve"}
_PD_SEVERITY = {"critical": "critical", "warning": "warning", "info": "info"}
_TEAMS_COLOR = {"critical": "attention", "warning": "warning", "info": "accent"}


def recipients(url: str) -> list[str]:
    """The addresses of a `mailto:` URL (comma-separated); ValueError saying what is wrong."""
    if not url.lower().startswith("mailto:"):
        raise ValueError("an email destination's URL is mailto:ADDRESS[,ADDRESS...]")
    addresses = [unquote(a).strip() for a in url[len("mailto:") :].split("?")[0].split(",")]
    addresses = [a for a in addresses if a]
    if not addresses:
        raise ValueError("the mailto: URL names no address")
    if len(addresses) > MAX_RECIPIENTS:
        raise ValueError(f"at most {MAX_RECIPIENTS} addresses")
    for a in addresses:
        local, _, domain = a.rpartition("@")
        if not local or "." not in domain or any(c.isspace() or c in "<>,;\"'" for c in a):
            raise ValueError(f"{a!r} is not an email address")
    return addresses


def check_target(fmt: str, url: str) -> str | None:
    """Why `url` cannot be a destination of format `fmt`, or None."""
    is_mail = url.lower().startswith("mailto:")
    if fmt == "email":
        try:
            recipients(url)
        except ValueError as exc:
            return str(exc)
        return None
    if is_mail:
        return "a mailto: URL is for the email format"
    return None


def _title(body: Mapping[str, Any]) -> str:
    alert = body.get("alert") or {}
    event = str(body.get("event", ""))
    vehicle = alert.get("vehicle_name") or alert.get("vehicle_id", "?")
    return (
        f"{str(alert.get('severity', '')).upper()} {alert.get('rule', '?')} "
        f"{_VERB.get(event, event)} on {vehicle}"
    )


def _facts(body: Mapping[str, Any]) -> list[tuple[str, str]]:
    alert = body.get("alert") or {}
    facts = [
        ("Vehicle", str(alert.get("vehicle_name") or alert.get("vehicle_id", ""))),
        ("Unit", f"{alert.get('bus', '?')} SA {alert.get('sa', '?')}"),
        ("Rule", str(alert.get("rule", ""))),
        ("Severity", str(alert.get("severity", ""))),
        ("State", str(alert.get("state", ""))),
    ]
    values = alert.get("values") or {}
    if values:
        facts.append(("Values", ", ".join(f"{k} {v}" for k, v in values.items())))
    if body.get("event") == "acknowledged" and alert.get("acknowledged_by"):
        ack = str(alert["acknowledged_by"])
        if alert.get("ack_comment"):
            ack += f": {alert['ack_comment']}"
        facts.append(("Acknowledged by", ack))
    facts.append(("Event", str(body.get("event_id", ""))))
    return facts


def teams_body(body: Mapping[str, Any]) -> dict[str, Any]:
    """A Teams message holding one Adaptive Card (incoming webhooks and Workflows take it)."""
    alert = body.get("alert") or {}
    link = body.get("links") or {}
    card: dict[str, Any] = {
        "$schema": "http://adaptivecards.io/schemas/adaptive-card.json",
        "type": "AdaptiveCard",
        "version": "1.4",
        "body": [
            {
                "type": "TextBlock",
                "text": _title(body),
                "weight": "Bolder",
                "size": "Medium",
                "wrap": True,
                "color": _TEAMS_COLOR.get(str(alert.get("severity", "")), "default"),
            },
            {"type": "TextBlock", "text": str(alert.get("message", "")), "wrap": True},
            {
                "type": "FactSet",
                "facts": [{"title": k, "value": v} for k, v in _facts(body)],
            },
        ],
        "actions": [
            {"type": "Action.OpenUrl", "title": title, "url": link[key]}
            for key, title in (("vehicle", "Vehicle"), ("alert", "Alert"))
            if link.get(key)
        ],
    }
    return {
        "type": "message",
        "summary": _title(body),
        "attachments": [
            {"contentType": "application/vnd.microsoft.card.adaptive", "content": card}
        ],
    }


def pagerduty_body(body: Mapping[str, Any], routing_key: str) -> dict[str, Any]:
    """A PagerDuty Events API v2 event: one incident per alert (`dedup_key`), triggered when
    raised, acknowledged and resolved as the alert is."""
    alert = body.get("alert") or {}
    event = str(body.get("event", ""))
    if event == "test":
        dedup = f"eqgw-{body.get('event_id', 'test')}"
    else:
        dedup = f"eqgw-alert-{alert.get('id', '')}"
    out: dict[str, Any] = {
        "routing_key": routing_key,
        "event_action": _PD_ACTION.get(event, "trigger"),
        "dedup_key": dedup,
    }
    if out["event_action"] == "trigger":
        ts = body.get("ts")
        link = body.get("links") or {}
        out["payload"] = {
            "summary": f"{_title(body)}: {alert.get('message', '')}"[:1024],
            "source": str(alert.get("vehicle_name") or alert.get("vehicle_id", "eqgw")),
            "severity": _PD_SEVERITY.get(str(alert.get("severity", "")), "info"),
            "timestamp": (
                time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime(float(ts))) if ts else None
            ),
            "component": f"{alert.get('bus', '')} SA {alert.get('sa', '')}",
            "group": str(alert.get("vehicle_id", "")),
            "class": str(alert.get("rule", "")),
            "custom_details": dict(_facts(body)),
        }
        out["links"] = [
            {"href": link[key], "text": title}
            for key, title in (("vehicle", "Vehicle"), ("alert", "Alert"))
            if link.get(key)
        ]
    return out


def message_id() -> str:
    """A Message-ID of email.utils.make_msgid's form, its random part from the system's
    generator: make_msgid draws it from the `random` module, moving that module's state in
    whatever program runs the gateway (tasks.backoff_delay says why that matters)."""
    return f"<{int(time.time() * 100)}.{os.getpid()}.{secrets.randbits(64)}@eqgw>"


def email_message(body: Mapping[str, Any], sender: str, to: list[str]) -> EmailMessage:
    """A plain-text email of an event."""
    alert = body.get("alert") or {}
    msg = EmailMessage()
    msg["Subject"] = f"[eqgw] {_title(body)}"
    msg["From"] = sender
    msg["To"] = ", ".join(to)
    msg["Date"] = formatdate(localtime=False)
    msg["Message-ID"] = message_id()
    msg["X-Eqgw-Event-Id"] = str(body.get("event_id", ""))
    lines = [_title(body), "", str(alert.get("message", "")), ""]
    lines += [f"{k}: {v}" for k, v in _facts(body)]
    link = body.get("links") or {}
    if link:
        lines += ["", *(f"{k.title()}: {v}" for k, v in link.items())]
    msg.set_content("\n".join(lines) + "\n")
    return msg


def _smtp_send(smtp: SmtpSettings, msg: EmailMessage, to: list[str], timeout: float) -> None:
    assert smtp.host is not None
    context = ssl.create_default_context(cafile=smtp.ca_file)
    server: smtplib.SMTP
    if smtp.tls == "tls":
        server = smtplib.SMTP_SSL(smtp.host, smtp.port, timeout=timeout, context=context)
    else:
        server = smtplib.SMTP(smtp.host, smtp.port, timeout=timeout)
    with server:
        if smtp.tls == "starttls":
            server.starttls(context=context)
        if smtp.username:
            server.login(smtp.username, smtp.password or "")
        server.send_message(msg, from_addr=smtp.sender, to_addrs=to)


async def send_email(
    smtp: SmtpSettings | None, url: str, body: Mapping[str, Any], timeout: float
) -> Attempt:
    """One message through the SMTP server within `timeout` (the attempt's bound, as for an
    HTTP destination: the dispatcher's claim lease counts on it); never raises (a failure is
    the attempt's outcome). A session cut by the bound may still complete in its thread: the
    event is then mailed twice at worst (delivery is at least once; `X-Eqgw-Event-Id`)."""
    start = time.monotonic()
    if smtp is None or not smtp.host:
        return Attempt(False, None, "no SMTP server is configured (EQGW_SMTP__HOST)", 0.0)
    try:
        to = recipients(url)
        msg = email_message(body, smtp.sender, to)
        async with asyncio.timeout(timeout):
            await asyncio.to_thread(_smtp_send, smtp, msg, to, timeout)
    except smtplib.SMTPResponseException as exc:
        err = exc.smtp_error
        text = err.decode(errors="replace") if isinstance(err, bytes) else str(err)
        error = f"SMTP {exc.smtp_code} {text}"
    except TimeoutError:
        error = f"TimeoutError: the SMTP session took longer than {timeout:g} s"
    except Exception as exc:  # any failure to hand the message over is this attempt's outcome
        error = f"{type(exc).__name__}: {str(exc) or type(exc).__name__}"
    else:
        return Attempt(True, None, None, time.monotonic() - start)
    return Attempt(False, None, error[:2000], time.monotonic() - start)


async def send(
    client: httpx.AsyncClient,
    hook: Mapping[str, Any],
    body: Mapping[str, Any],
    *,
    delivery_id: int,
    now: float,
    timeout: float,
    smtp: SmtpSettings | None = None,
) -> Attempt:
    """Hand one event body to the destination `hook` (its format, url and secret) once."""
    fmt = hook["format"]
    if fmt == "email":
        return await send_email(smtp, hook["url"], body, timeout)
    if fmt in ("teams", "pagerduty"):
        data = teams_body(body) if fmt == "teams" else pagerduty_body(body, hook["secret"])
        headers = {
            "Content-Type": "application/json",
            "User-Agent": USER_AGENT,
            EVENT_ID_HEADER: str(body.get("event_id", "")),
            EVENT_HEADER: str(body.get("event", "")),
            DELIVERY_HEADER: str(delivery_id),
        }
        return await post(client, hook["url"], orjson.dumps(data), headers, timeout)
    content, headers = render(fmt, body, hook["secret"], delivery_id=delivery_id, now=now)
    return await post(client, hook["url"], content, headers, timeout)
