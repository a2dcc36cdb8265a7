"""Webhook endpoints (admin only): create, list, change, delete, send a test, the delivery log."""

from __future__ import annotations

import time
from typing import Any, Literal
from urllib.parse import urlsplit

from fastapi import APIRouter, Path, Query, Request
from pydantic import BaseModel, ConfigDict, Field, field_validator

from eqgw.notify import repository as q
from eqgw.notify.destinations import check_url, parse_networks, redact_url
from eqgw.notify.senders import check_target, recipients
from eqgw.notify.webhooks import new_secret, signing_key
from eqgw.security.auth import FleetAdminRead, FleetAdminWrite
from eqgw.security.keys import Principal
from eqgw.web.errors import ApiError
from eqgw.web.responses import JsonResponse
from eqgw.web.runtime import Rt, Runtime
from eqgw.web.schemas import MAX_ID, RequestBody, _body_schema, errors

router = APIRouter(tags=["webhooks"], responses=errors(401, 403))

Severity = Literal["info", "warning", "critical"]
Kind = Literal["raised", "acknowledged", "cleared"]
Format = Literal["json", "slack", "teams", "pagerduty", "email"]
FORMAT_DESCRIPTION = (
    "json (signed), slack, teams (an Adaptive Card), pagerduty (Events API v2; the secret is "
    "the routing key) or email (the URL is mailto:ADDRESS[,ADDRESS...]; the smtp settings)"
)


# What _check_url takes, for the schema (narrower: a host name with a letter in its last
# label, so it names no address; IPv6 literals aside): http(s)://, a host, a port 1-65535;
# or mailto: addresses (email).
_PORT = r"(6553[0-5]|655[0-2]\d|65[0-4]\d\d|6[0-4]\d{3}|[1-5]\d{4}|[1-9]\d{0,3})"
_HTTP = (
    r"[hH][tT][tT][pP][sS]?://([^\s/?#@\x00]+@)?"
    r"([A-Za-z0-9-]{1,63}\.)*[A-Za-z][A-Za-z0-9-]{0,62}"
    rf"(:{_PORT})?([/?#][^\s\x00]*)?"
)
# mailto: and 1 to 20 addresses with a dot in their domain (no quoting, no query).
_ADDRESS = r"[^\s@,<>;\"'?%\x00]+@[^\s@,<>;\"'?%.\x00]+(\.[^\s@,<>;\"'?%.\x00]+)+"
_MAILTO = rf"[mM][aA][iI][lL][tT][oO]:{_ADDRESS}(,{_ADDRESS}){{0,19}}"
URL_PATTERN = rf"^({_HTTP}|{_MAILTO})$"


def _check_url(url: str) -> str:
    if url.lower().startswith("mailto:"):
        recipients(url)  # a ValueError saying what is wrong
        return url
    parts = urlsplit(url)
    if parts.scheme not in ("http", "https"):
        raise ValueError("the URL must start with http:// or https:// (mailto: for email)")
    if not parts.hostname:
        raise ValueError("the URL has no host")
    # `http://host:/hook` would be read as port 80: a port, when the URL has a colon for one,
    # is a number from 1 to 65535.
    hostport = parts.netloc.rpartition("@")[2]
    if hostport.endswith(":"):
        raise ValueError("the URL's port is empty (give one, or leave out the colon)")
    try:
        port = parts.port
    except ValueError:
        raise ValueError("the URL's port is not a number from 1 to 65535") from None
    if port == 0:
        raise ValueError("the URL's port is not a number from 1 to 65535")
    if any(c.isspace() for c in url):
        raise ValueError("the URL must not contain spaces")
    return url


class _Filters(RequestBody):
    min_severity: Severity | None = Field(
        default=None, description="Only alerts of this severity or worse (null: all)"
    )
    kinds: list[Kind] | None = Field(
        default=None, min_length=1, max_length=3, description="Only these events (null: all)"
    )
    vehicles: list[str] | None = Field(
        default=None, min_length=1, max_length=1000, description="Only these vehicle ids"
    )
    rules: list[str] | None = Field(
        default=None, min_length=1, max_length=1000, description="Only these rule ids"
    )


SECRET_DESCRIPTION = (
    "`whsec_` and base64 (Standard Webhooks; the HMAC key is the decoded bytes), or any other "
    "text (the key is its UTF-8 bytes). Omitted: one is generated."
)


def _check_secret(v: str | None) -> str | None:
    if v is not None:
        signing_key(v)  # a SecretError (a ValueError) is a 422 saying why
    return v


class WebhookCreate(_Filters):
    """A new webhook; without `secret` one is generated. The secret is in the reply only."""

    model_config = ConfigDict(extra="forbid")

    name: str = Field(min_length=1, max_length=200)
    url: str = Field(
        min_length=1,
        max_length=2000,
        description="http:// or https://; mailto: for email",
        json_schema_extra={"pattern": URL_PATTERN},  # declared; _check_url decides
    )
    secret: str | None = Field(
        default=None, min_length=16, max_length=200, description=SECRET_DESCRIPTION
    )
    format: Format = Field(default="json", description=FORMAT_DESCRIPTION)
    enabled: bool = True

    _url = field_validator("url")(_check_url)
    _secret = field_validator("secret")(_check_secret)


_NOT_NULL = ("name", "url", "secret", "format", "enabled")


def _update_schema(schema: dict[str, Any]) -> None:
    """The update's schema as the route takes it: these fields may be left out, not null."""
    _body_schema(schema)
    for name in _NOT_NULL:
        prop = schema["properties"][name]
        kinds = [k for k in prop.pop("anyOf", []) if k.get("type") != "null"]
        if len(kinds) == 1:  # what the field itself declares (a pattern) wins
            prop.update({k: v for k, v in kinds[0].items() if k not in prop})
        elif kinds:
            prop["anyOf"] = kinds


class WebhookUpdate(_Filters):
    """Changes to a webhook: only the fields given change (`null` clears a filter; the other
    fields cannot be null)."""

    model_config = ConfigDict(extra="forbid", json_schema_extra=_update_schema)

    name: str | None = Field(default=None, min_length=1, max_length=200)
    url: str | None = Field(
        default=None,
        min_length=1,
        max_length=2000,
        json_schema_extra={"pattern": URL_PATTERN},  # declared; _check_url decides
    )
    secret: str | None = Field(
        default=None, min_length=16, max_length=200, description=SECRET_DESCRIPTION
    )
    _secret = field_validator("secret")(_check_secret)
    rotate_secret: bool = Field(default=False, description="Generate a new secret (in the reply)")
    format: Format | None = Field(default=None, description=FORMAT_DESCRIPTION)
    enabled: bool | None = None

    @field_validator("url")
    @classmethod
    def _url_ok(cls, v: str | None) -> str | None:
        return None if v is None else _check_url(v)


class DeliveryCounts(BaseModel):
    pending: int
    delivered: int
    failed: int


class WebhookOut(BaseModel):
    """A webhook as listed (never its secret)."""

    id: int
    name: str
    url: str
    format: str
    enabled: bool
    min_severity: str | None
    kinds: list[str] | None
    vehicles: list[str] | None
    rules: list[str] | None
    created_at: float
    updated_at: float
    deliveries: DeliveryCounts


class WebhookWithSecret(WebhookOut):
    """A webhook just created (or its secret just changed): `secret` is shown this once."""

    secret: str


class DeliveryOut(BaseModel):
    """One line of the delivery log: an alert event (or a test) for this webhook."""

    id: int
    webhook_id: int
    event_id: int | None
    kind: str
    alert_id: int | None
    state: str = Field(description="pending, delivered or failed")
    attempts: int
    created_at: float
    next_attempt_at: float
    last_attempt_at: float | None
    last_status: int | None
    last_error: str | None
    delivered_at: float | None


class DeliveryLog(BaseModel):
    deliveries: list[DeliveryOut]


class TestResult(BaseModel):
    """The outcome of a test send (also in the delivery log, kind `test`)."""

    delivered: bool
    status: int | None = Field(description="HTTP status, null when no response came")
    error: str | None
    duration_ms: float
    event_id: str
    delivery_id: int


async def _webhook(rt: Runtime, webhook_id: int) -> dict[str, Any]:
    hook: dict[str, Any] | None = await rt.db(q.get_webhook, webhook_id)
    if hook is None:
        raise ApiError(404, f"no webhook {webhook_id}", "unknown_webhook")
    return _shown(hook)


def _shown(hook: dict[str, Any]) -> dict[str, Any]:
    """A webhook as the API shows it: its URL without credentials."""
    return {**hook, "url": redact_url(hook["url"], hook.get("format"))}


async def _check_destination(
    rt: Runtime,
    who: Principal,
    action: str,
    url: str,
    body: BaseModel,
    target: str | None = None,
    fmt: str = "json",
) -> None:
    """Refuse (422, audited) a URL that does not suit the format, or whose host resolves to an
    address webhooks may not reach (an email's SMTP server is the operator's setting)."""
    reason = check_target(fmt, url)
    if reason is None and fmt != "email":
        reason = await check_url(url, parse_networks(rt.settings.webhook_allow_networks))
    if (
        reason is None
        and fmt == "pagerduty"
        and isinstance(body, WebhookCreate)
        and not body.secret
    ):
        reason = "a pagerduty destination needs its routing key as `secret`"
    if reason is None:
        return
    await rt.audit(
        who,
        action,
        outcome="refused",
        status=422,
        target=target,
        detail=reason,
        request=_audit_request(body),
    )
    raise ApiError(422, reason, "destination_refused")


def _delivery(request: Request) -> Any:
    return getattr(request.app.state, "delivery", None)


def _audit_request(body: BaseModel) -> dict[str, Any]:
    data = body.model_dump(exclude_unset=True)
    if "secret" in data:
        data["secret"] = "***"
    if data.get("url"):
        data["url"] = redact_url(data["url"], data.get("format"))
    return data


@router.post(
    "/webhooks",
    status_code=201,
    response_model=WebhookWithSecret,
    responses=errors(400, 409, 422, 429),
)
async def post_webhook(
    body: WebhookCreate,
    who: FleetAdminWrite,
    rt: Rt,
) -> JsonResponse:
    """Create a webhook; its secret (given or generated) is in this response only."""
    await rt.check_write_rate(who, "webhook.create")
    if await rt.db(q.webhook_name_taken, body.name):
        await rt.audit(
            who,
            "webhook.create",
            outcome="refused",
            status=409,
            detail=f"name {body.name!r} taken",
            request=_audit_request(body),
        )
        raise ApiError(409, f"a webhook named {body.name!r} exists", "webhook_name_taken")
    await _check_destination(rt, who, "webhook.create", body.url, body, fmt=body.format)
    now = time.time()
    secret = body.secret or new_secret()
    row = {**body.model_dump(exclude={"secret"}), "secret": secret}
    webhook_id = await rt.db(q.create_webhook, {**row, "created_at": now, "updated_at": now})
    await rt.audit(
        who,
        "webhook.create",
        outcome="accepted",
        status=201,
        target=f"webhook {webhook_id}",
        request=_audit_request(body),
    )
    hook = await _webhook(rt, webhook_id)
    return JsonResponse({**hook, "secret": secret}, status_code=201)


@router.get("/webhooks", response_model=list[WebhookOut])
async def get_webhooks(
    _who: FleetAdminRead,
    rt: Rt,
) -> JsonResponse:
    """Every webhook with its deliveries counted by state (never the secrets)."""
    return JsonResponse([_shown(h) for h in await rt.db(q.list_webhooks)])


@router.get("/webhooks/{webhook_id}", response_model=WebhookOut, responses=errors(404, 422))
async def get_webhook(
    *,
    webhook_id: int = Path(ge=1, le=MAX_ID),
    _who: FleetAdminRead,
    rt: Rt,
) -> JsonResponse:
    """One webhook."""
    return JsonResponse(await _webhook(rt, webhook_id))


@router.patch(
    "/webhooks/{webhook_id}",
    response_model=WebhookOut | WebhookWithSecret,
    responses=errors(400, 404, 409, 422, 429),
)
async def patch_webhook(
    *,
    body: WebhookUpdate,
    webhook_id: int = Path(ge=1, le=MAX_ID),
    who: FleetAdminWrite,
    rt: Rt,
) -> JsonResponse:
    """Change a webhook; a new secret (given, or `rotate_secret`) is in this response only."""
    await rt.check_write_rate(who, "webhook.update")
    target = f"webhook {webhook_id}"
    existing = await rt.db(q.get_webhook, webhook_id)
    if existing is None:
        await rt.audit(who, "webhook.update", outcome="refused", status=404, target=target)
        raise ApiError(404, f"no webhook {webhook_id}", "unknown_webhook")
    changes = body.model_dump(exclude_unset=True, exclude={"rotate_secret"})
    for required in _NOT_NULL:
        if required in changes and changes[required] is None:
            raise ApiError(422, f"{required} cannot be null", "validation_error")
    if body.rotate_secret:
        if body.secret is not None:
            raise ApiError(422, "give either secret or rotate_secret", "validation_error")
        changes["secret"] = new_secret()
    if body.name is not None and await rt.db(q.webhook_name_taken, body.name, webhook_id):
        await rt.audit(
            who,
            "webhook.update",
            outcome="refused",
            status=409,
            target=target,
            detail=f"name {body.name!r} taken",
            request=_audit_request(body),
        )
        raise ApiError(409, f"a webhook named {body.name!r} exists", "webhook_name_taken")
    if body.url is not None or body.format is not None:
        url, fmt = body.url or existing["url"], body.format or existing["format"]
        await _check_destination(rt, who, "webhook.update", url, body, target, fmt)
    if changes:
        await rt.db(q.update_webhook, webhook_id, {**changes, "updated_at": time.time()})
    await rt.audit(
        who,
        "webhook.update",
        outcome="accepted",
        status=200,
        target=target,
        request=_audit_request(body),
    )
    hook = await _webhook(rt, webhook_id)
    if "secret" in changes:
        hook["secret"] = changes["secret"]
    return JsonResponse(hook)


@router.delete("/webhooks/{webhook_id}", response_model=WebhookOut, responses=errors(404, 422))
async def delete_webhook(
    *,
    webhook_id: int = Path(ge=1, le=MAX_ID),
    who: FleetAdminWrite,
    rt: Rt,
) -> JsonResponse:
    """Delete a webhook with its delivery log; what is still pending is dropped."""
    target = f"webhook {webhook_id}"
    hook = await rt.db(q.get_webhook, webhook_id)
    if hook is None or not await rt.db(q.delete_webhook, webhook_id):
        await rt.audit(who, "webhook.delete", outcome="refused", status=404, target=target)
        raise ApiError(404, f"no webhook {webhook_id}", "unknown_webhook")
    await rt.audit(who, "webhook.delete", outcome="accepted", status=200, target=target)
    return JsonResponse(_shown(hook))


@router.post(
    "/webhooks/{webhook_id}/test",
    response_model=TestResult,
    responses=errors(404, 422, 429, 503),
)
async def post_webhook_test(
    *,
    request: Request,
    webhook_id: int = Path(ge=1, le=MAX_ID),
    who: FleetAdminWrite,
    rt: Rt,
) -> JsonResponse:
    """POST a signed test event to the webhook now (even if disabled) and report the outcome."""
    await rt.check_write_rate(who, "webhook.test")
    hook = await rt.db(q.get_webhook, webhook_id, with_secret=True)
    target = f"webhook {webhook_id}"
    if hook is None:
        await rt.audit(who, "webhook.test", outcome="refused", status=404, target=target)
        raise ApiError(404, f"no webhook {webhook_id}", "unknown_webhook")
    delivery = _delivery(request)
    if delivery is None:
        raise ApiError(503, "alert delivery is not running")
    result = await delivery.send_test(hook)
    await rt.audit(
        who,
        "webhook.test",
        outcome="done",
        status=200,
        target=target,
        detail="delivered" if result["delivered"] else f"not delivered: {result['error']}",
    )
    return JsonResponse(result)


@router.get(
    "/webhooks/{webhook_id}/deliveries", response_model=DeliveryLog, responses=errors(404, 422)
)
async def get_deliveries(
    *,
    webhook_id: int = Path(ge=1, le=MAX_ID),
    state: Literal["pending", "delivered", "failed"] | None = None,
    before: int | None = Query(default=None, ge=1, le=MAX_ID, description="Delivery id to page"),
    limit: int = Query(default=100, ge=1, le=1000),
    _who: FleetAdminRead,
    rt: Rt,
) -> JsonResponse:
    """The delivery log, newest first: one line per alert event (and test), its attempts, the
    last HTTP status or error, when it is tried next."""
    await _webhook(rt, webhook_id)
    rows = await rt.db(q.list_deliveries, webhook_id, state=state, before_id=before, limit=limit)
    return JsonResponse({"deliveries": rows})
