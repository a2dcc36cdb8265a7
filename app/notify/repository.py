"""Queries of alert delivery: webhooks, the outbox (fan-out, claims, results), cursors.

Each takes a sync Connection inside the caller's transaction. The outbox is `alert_events`
(written by the alert engine in the same transaction as each alert change), read past a cursor:
the fan-out turns each new event into one `webhook_deliveries` row per matching webhook, in one
transaction with the cursor's advance, so an event is queued for a webhook exactly once.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from sqlalchemy import Connection, Table, and_, delete, func, insert, select, update
from sqlalchemy.dialects.postgresql import insert as pg_insert
from sqlalchemy.dialects.sqlite import insert as sqlite_insert

from eqgw.store.models import Alert, AlertEvent, AlertRule, table_of
from eqgw.store.webhook_models import DeliveryCursor, Webhook, WebhookDelivery

_hooks = table_of(Webhook)
_deliveries = table_of(WebhookDelivery)
_cursors = table_of(DeliveryCursor)
_events = table_of(AlertEvent)
_rules = table_of(AlertRule)
_alerts = table_of(Alert)

SEVERITY_RANK = {"info": 0, "warning": 1, "critical": 2}
EVENT_KINDS = ("raised", "acknowledged", "cleared")
WEBHOOKS_CURSOR = "webhooks"
MQTT_CURSOR = "mqtt"


@dataclass(frozen=True, slots=True)
class OutboxEvent:
    """One row of `alert_events`, with the targets of its rule (empty: everywhere)."""

    id: int
    alert_id: int
    kind: str
    ts: float
    payload: dict[str, Any]
    muted: bool
    targets: tuple[str, ...] = ()

    @property
    def alert(self) -> dict[str, Any]:
        alert = self.payload.get("alert")
        return alert if isinstance(alert, dict) else {}


def _pg(conn: Connection) -> bool:
    return conn.dialect.name == "postgresql"


def _insert_ignore(conn: Connection, table: Table) -> Any:
    """INSERT ... ON CONFLICT DO NOTHING on either engine."""
    return (pg_insert if _pg(conn) else sqlite_insert)(table)


# -- webhooks -----------------------------------------------------------------------------

PUBLIC_COLUMNS = [c for c in _hooks.c if c.name != "secret"]


def create_webhook(conn: Connection, row: Mapping[str, Any]) -> int:
    """Store a webhook; returns its id."""
    webhook_id: int = conn.execute(insert(_hooks).values(**row).returning(_hooks.c.id)).scalar_one()
    return webhook_id


def webhook_name_taken(conn: Connection, name: str, except_id: int | None = None) -> bool:
    """Whether another webhook has this name."""
    stmt = select(_hooks.c.id).where(_hooks.c.name == name)
    if except_id is not None:
        stmt = stmt.where(_hooks.c.id != except_id)
    return conn.execute(stmt).first() is not None


def list_webhooks(conn: Connection) -> list[dict[str, Any]]:
    """Every webhook without its secret, with its deliveries counted by state."""
    counts = delivery_counts(conn)
    rows = conn.execute(select(*PUBLIC_COLUMNS).order_by(_hooks.c.id))
    return [{**r._mapping, "deliveries": counts.get(r.id, _no_counts())} for r in rows]


def get_webhook(
    conn: Connection, webhook_id: int, *, with_secret: bool = False
) -> dict[str, Any] | None:
    """One webhook (its secret only when asked), with its deliveries counted by state."""
    cols = list(_hooks.c) if with_secret else PUBLIC_COLUMNS
    row = conn.execute(select(*cols).where(_hooks.c.id == webhook_id)).first()
    if row is None:
        return None
    counts = delivery_counts(conn, webhook_id)
    return {**row._mapping, "deliveries": counts.get(webhook_id, _no_counts())}


def update_webhook(conn: Connection, webhook_id: int, values: Mapping[str, Any]) -> bool:
    """Change a webhook; False when there is none."""
    result = conn.execute(update(_hooks).where(_hooks.c.id == webhook_id).values(**values))
    return bool(result.rowcount)


def delete_webhook(conn: Connection, webhook_id: int) -> bool:
    """Remove a webhook and its delivery log; False when there is none."""
    conn.execute(delete(_deliveries).where(_deliveries.c.webhook_id == webhook_id))
    result = conn.execute(delete(_hooks).where(_hooks.c.id == webhook_id))
    return bool(result.rowcount)


def _no_counts() -> dict[str, int]:
    return {"pending": 0, "delivered": 0, "failed": 0}


def delivery_counts(conn: Connection, webhook_id: int | None = None) -> dict[int, dict[str, int]]:
    """Deliveries per webhook and state (test sends included)."""
    stmt = select(_deliveries.c.webhook_id, _deliveries.c.state, func.count()).group_by(
        _deliveries.c.webhook_id, _deliveries.c.state
    )
    if webhook_id is not None:
        stmt = stmt.where(_deliveries.c.webhook_id == webhook_id)
    out: dict[int, dict[str, int]] = {}
    for wid, state, n in conn.execute(stmt):
        out.setdefault(wid, _no_counts())[state] = n
    return out


def list_deliveries(
    conn: Connection,
    webhook_id: int,
    *,
    state: str | None = None,
    before_id: int | None = None,
    limit: int = 100,
) -> list[dict[str, Any]]:
    """The delivery log of a webhook, newest first."""
    stmt = select(_deliveries).where(_deliveries.c.webhook_id == webhook_id)
    if state is not None:
        stmt = stmt.where(_deliveries.c.state == state)
    if before_id is not None:
        stmt = stmt.where(_deliveries.c.id < before_id)
    stmt = stmt.order_by(_deliveries.c.id.desc()).limit(limit)
    return [dict(r._mapping) for r in conn.execute(stmt)]


def add_test_delivery(conn: Connection, row: Mapping[str, Any]) -> int:
    """Log a test send (not an alert event: no event id, never retried)."""
    delivery_id: int = conn.execute(
        insert(_deliveries).values(**row).returning(_deliveries.c.id)
    ).scalar_one()
    return delivery_id


def finish_test_delivery(conn: Connection, delivery_id: int, values: Mapping[str, Any]) -> None:
    """Record the outcome of a test send logged by `add_test_delivery`."""
    conn.execute(update(_deliveries).where(_deliveries.c.id == delivery_id).values(**values))


# -- the outbox: reading alert_events past a cursor --------------------------------------


def readable_count(
    after: int, ids: Sequence[int], gaps: dict[int, float], now: float, wait_s: float
) -> int:
    """How many of `ids` (ascending, all above `after`) may be handled now.

    A missing id may belong to a transaction that has not committed yet (PostgreSQL hands out
    ids before commit): the ids past it wait until it shows up, or until it has been missing for
    `wait_s` (a rolled-back transaction never fills it). `gaps` remembers when each gap was
    first seen, across calls.
    """
    expected = after + 1
    n = 0
    for event_id in ids:
        if event_id != expected:
            first_seen = gaps.setdefault(expected, now)
            if now - first_seen < wait_s:
                break
            del gaps[expected]
        n += 1
        expected = event_id + 1
    for stale in [g for g in gaps if g <= after]:
        del gaps[stale]
    return n


def events_after(conn: Connection, after: int, limit: int) -> list[OutboxEvent]:
    """Alert events with an id above `after`, oldest first, with their rule's targets."""
    rows = conn.execute(
        select(_events).where(_events.c.id > after).order_by(_events.c.id).limit(limit)
    ).all()
    rules = {str(r.get("rule")) for r in (row.payload.get("alert") or {} for row in rows)}
    targets = _rule_targets(conn, rules) if rows else {}
    out = []
    for r in rows:
        payload = r.payload if isinstance(r.payload, dict) else {}
        rule = (payload.get("alert") or {}).get("rule")
        out.append(
            OutboxEvent(
                id=r.id,
                alert_id=r.alert_id,
                kind=r.kind,
                ts=r.ts,
                payload=payload,
                muted=bool(r.muted),
                targets=targets.get(str(rule), ()),
            )
        )
    return out


def _rule_targets(conn: Connection, rules: Iterable[str]) -> dict[str, tuple[str, ...]]:
    rows = conn.execute(
        select(_rules.c.id, _rules.c.targets).where(_rules.c.id.in_(sorted(rules)))
    ).all()
    return {r.id: tuple(str(t) for t in (r.targets or ())) for r in rows}


def max_event_id(conn: Connection) -> int:
    """The highest alert_events id (0 when there is none)."""
    n: int | None = conn.execute(select(func.max(_events.c.id))).scalar_one()
    return n or 0


def first_publish_position(conn: Connection) -> int:
    """Where a new publishing cursor starts: past the history, but before the first event of
    every alert not cleared yet, so a subscriber sees each open alert raised before it sees
    the alert acknowledged or cleared."""
    open_alerts = select(_alerts.c.id).where(_alerts.c.cleared_at.is_(None))
    first: int | None = conn.execute(
        select(func.min(_events.c.id)).where(_events.c.alert_id.in_(open_alerts))
    ).scalar_one()
    newest = max_event_id(conn)
    return newest if first is None else min(newest, first - 1)


def read_cursor(conn: Connection, name: str, *, lock: bool = False) -> int | None:
    """A cursor's position; with `lock`, the row stays locked until commit (PostgreSQL)."""
    stmt = select(_cursors.c.last_event_id).where(_cursors.c.name == name)
    if lock and _pg(conn):
        stmt = stmt.with_for_update()
    value: int | None = conn.execute(stmt).scalar_one_or_none()
    return value


def ensure_cursor(conn: Connection, name: str, start: int, now: float) -> int:
    """Create a cursor at `start` unless it exists; returns its position."""
    stmt = _insert_ignore(conn, _cursors).values(name=name, last_event_id=start, updated_at=now)
    conn.execute(stmt.on_conflict_do_nothing(index_elements=["name"]))
    pos = read_cursor(conn, name)
    assert pos is not None
    return pos


def advance_cursor(conn: Connection, name: str, last_event_id: int, now: float) -> None:
    """Move a cursor forward (never back)."""
    conn.execute(
        update(_cursors)
        .where(_cursors.c.name == name, _cursors.c.last_event_id < last_event_id)
        .values(last_event_id=last_event_id, updated_at=now)
    )


def take_cursor_lease(conn: Connection, name: str, owner: str, now: float, lease_s: float) -> bool:
    """Become (or stay) the one process reading a cursor for `lease_s`; False if another is."""
    result = conn.execute(
        update(_cursors)
        .where(
            _cursors.c.name == name,
            (_cursors.c.owner.is_(None))
            | (_cursors.c.owner == owner)
            | (_cursors.c.lease_until.is_(None))
            | (_cursors.c.lease_until < now),
        )
        .values(owner=owner, lease_until=now + lease_s)
    )
    return bool(result.rowcount)


def release_cursor_lease(conn: Connection, name: str, owner: str) -> None:
    """Give up a cursor's lease (on a clean stop), so another process takes over at once."""
    conn.execute(
        update(_cursors)
        .where(_cursors.c.name == name, _cursors.c.owner == owner)
        .values(owner=None, lease_until=None)
    )


def webhook_matches(hook: Mapping[str, Any], event: OutboxEvent) -> bool:
    """Whether a webhook's filters (and the event rule's targets) let an event through."""
    if event.targets and hook["name"] not in event.targets:
        return False
    alert = event.alert
    kinds = hook.get("kinds")
    if kinds and event.kind not in kinds:
        return False
    vehicles = hook.get("vehicles")
    if vehicles and alert.get("vehicle_id") not in vehicles:
        return False
    rules = hook.get("rules")
    if rules and alert.get("rule") not in rules:
        return False
    floor = hook.get("min_severity")
    if floor:
        # An unknown severity is delivered rather than silently filtered out.
        rank = SEVERITY_RANK.get(str(alert.get("severity")), max(SEVERITY_RANK.values()))
        if rank < SEVERITY_RANK.get(floor, 0):
            return False
    return True


@dataclass(frozen=True, slots=True)
class FanOut:
    """What one fan-out round did."""

    events: int
    queued: int
    cursor: int


def fan_out(
    conn: Connection, *, now: float, gaps: dict[int, float], gap_wait_s: float, limit: int
) -> FanOut:
    """Queue the events past the webhook cursor for every enabled, matching webhook.

    The cursor row is locked (PostgreSQL) for the transaction, so with several gateways on one
    database one fans out at a time; muted events are passed over.
    """
    after = read_cursor(conn, WEBHOOKS_CURSOR, lock=True)
    if after is None:
        after = ensure_cursor(conn, WEBHOOKS_CURSOR, 0, now)
    events = events_after(conn, after, limit)
    events = events[: readable_count(after, [e.id for e in events], gaps, now, gap_wait_s)]
    if not events:
        return FanOut(0, 0, after)
    hooks = [
        dict(r._mapping)
        for r in conn.execute(select(*PUBLIC_COLUMNS).where(_hooks.c.enabled.is_(True)))
    ]
    rows = [
        {
            "webhook_id": hook["id"],
            "event_id": event.id,
            "kind": event.kind,
            "alert_id": event.alert_id,
            "state": "pending",
            "attempts": 0,
            "created_at": now,
            "next_attempt_at": now,
        }
        for event in events
        if not event.muted
        for hook in hooks
        if webhook_matches(hook, event)
    ]
    if rows:
        stmt = _insert_ignore(conn, _deliveries).on_conflict_do_nothing(
            index_elements=["webhook_id", "event_id"]
        )
        conn.execute(stmt, rows)
    advance_cursor(conn, WEBHOOKS_CURSOR, events[-1].id, now)
    return FanOut(len(events), len(rows), events[-1].id)


# -- the outbox: claiming and recording deliveries ----------------------------------------


def claim_due(conn: Connection, *, now: float, lease_s: float, limit: int) -> list[dict[str, Any]]:
    """Claim up to `limit` deliveries of enabled webhooks, in event order per webhook: a
    webhook's deliveries are claimed only while its oldest pending one is due, and then as one
    run from that oldest on, so a webhook receives its events strictly in order (whatever the
    retry time of each). Claimed rows are leased for `lease_s` (their next attempt time moves
    past the lease, so a process that dies mid-send leaves them to be retried, and nobody else
    claims that webhook meanwhile). PostgreSQL locks the webhooks it claims for (skipping those
    another gateway is claiming at the same moment), so one gateway at a time sends a webhook's
    run."""
    due_hooks = (
        select(_hooks.c.id)
        .where(
            _hooks.c.enabled.is_(True),
            _hooks.c.id.in_(
                select(_deliveries.c.webhook_id).where(
                    _deliveries.c.state == "pending", _deliveries.c.next_attempt_at <= now
                )
            ),
        )
        .order_by(_hooks.c.id)
    )
    if _pg(conn):
        due_hooks = due_hooks.with_for_update(skip_locked=True, key_share=True)
    hook_ids = list(conn.execute(due_hooks).scalars())
    if not hook_ids:
        return []
    # Each webhook's oldest pending deliveries (at most `limit` of each), oldest first.
    ranked = (
        select(
            _deliveries.c.id,
            _deliveries.c.webhook_id,
            _deliveries.c.next_attempt_at,
            func.row_number()
            .over(partition_by=_deliveries.c.webhook_id, order_by=_deliveries.c.event_id)
            .label("n"),
        )
        .where(_deliveries.c.state == "pending", _deliveries.c.webhook_id.in_(hook_ids))
        .subquery()
    )
    heads = conn.execute(
        select(ranked.c.id, ranked.c.webhook_id, ranked.c.next_attempt_at, ranked.c.n)
        .where(ranked.c.n <= limit)
        .order_by(ranked.c.webhook_id, ranked.c.n)
    ).all()
    ids: list[int] = []
    blocked: set[int] = set()
    for row in heads:
        if len(ids) >= limit:
            break
        # The oldest not due (waiting for its retry, or leased by a sender): none of this
        # webhook's later deliveries may overtake it.
        if row.n == 1 and row.next_attempt_at > now:
            blocked.add(row.webhook_id)
        if row.webhook_id not in blocked:
            ids.append(row.id)
    if not ids:
        return []
    conn.execute(
        update(_deliveries).where(_deliveries.c.id.in_(ids)).values(next_attempt_at=now + lease_s)
    )
    rows = conn.execute(
        select(
            _deliveries,
            _hooks.c.name.label("webhook_name"),
            _hooks.c.url,
            _hooks.c.secret,
            _hooks.c.format,
            _events.c.ts.label("event_ts"),
            _events.c.payload,
        )
        .join(_hooks, _hooks.c.id == _deliveries.c.webhook_id)
        .join(_events, _events.c.id == _deliveries.c.event_id, isouter=True)
        .where(_deliveries.c.id.in_(ids))
        .order_by(_deliveries.c.webhook_id, _deliveries.c.event_id)
    )
    return [dict(r._mapping) for r in rows]


def record_attempt(
    conn: Connection,
    delivery_id: int,
    *,
    now: float,
    delivered: bool,
    status: int | None,
    error: str | None,
    next_attempt_at: float | None = None,
    give_up: bool = False,
) -> None:
    """Record one attempt: delivered, or failed with the time of the next (or given up)."""
    values: dict[str, Any] = {
        "attempts": _deliveries.c.attempts + 1,
        "last_attempt_at": now,
        "last_status": status,
        "last_error": error[:2000] if error else None,
    }
    if delivered:
        values.update(state="delivered", delivered_at=now, next_attempt_at=now)
    elif give_up:
        values.update(state="failed", next_attempt_at=now)
    else:
        assert next_attempt_at is not None
        values.update(next_attempt_at=next_attempt_at)
    conn.execute(
        update(_deliveries)
        .where(_deliveries.c.id == delivery_id, _deliveries.c.state == "pending")
        .values(**values)
    )


def postpone(conn: Connection, delivery_ids: Sequence[int], until: float) -> None:
    """Move claimed but unattempted deliveries to `until` (their webhook is failing)."""
    if delivery_ids:
        conn.execute(
            update(_deliveries)
            .where(_deliveries.c.id.in_(list(delivery_ids)), _deliveries.c.state == "pending")
            .values(next_attempt_at=until)
        )


def renew_claim(
    conn: Connection, delivery_ids: Sequence[int], *, until: float, new_until: float
) -> bool:
    """Extend the lease of a claimed run, all of it or nothing: False when any of its rows is
    no longer held under `until` (its lease ran out and another process claimed it, or it was
    given up). The lease time is the claim's token: another claim sets its own."""
    ids = list(delivery_ids)
    if not ids:
        return True
    held = (
        select(_deliveries.c.id)
        .where(
            _deliveries.c.id.in_(ids),
            _deliveries.c.state == "pending",
            _deliveries.c.next_attempt_at == until,
        )
        .order_by(_deliveries.c.id)
    )
    if _pg(conn):
        held = held.with_for_update()
    if len(conn.execute(held).all()) != len(ids):
        return False
    conn.execute(
        update(_deliveries).where(_deliveries.c.id.in_(ids)).values(next_attempt_at=new_until)
    )
    return True


def release(conn: Connection, claims: Mapping[int, float], now: float) -> None:
    """Make claimed deliveries due again at once (a clean stop before they were sent), those
    still held under their claim's lease (`claims`: id -> lease time) only."""
    by_lease: dict[float, list[int]] = {}
    for delivery_id, until in claims.items():
        by_lease.setdefault(until, []).append(delivery_id)
    for until, ids in by_lease.items():
        conn.execute(
            update(_deliveries)
            .where(
                _deliveries.c.id.in_(ids),
                _deliveries.c.state == "pending",
                _deliveries.c.next_attempt_at == until,
            )
            .values(next_attempt_at=now)
        )


def give_up_expired(conn: Connection, *, now: float, after_s: float) -> list[dict[str, Any]]:
    """Mark failed every pending delivery queued more than `after_s` ago; returns them."""
    cond = and_(_deliveries.c.state == "pending", _deliveries.c.created_at < now - after_s)
    rows = [
        dict(r._mapping)
        for r in conn.execute(
            select(
                _deliveries.c.id,
                _deliveries.c.webhook_id,
                _deliveries.c.event_id,
                _deliveries.c.attempts,
                _deliveries.c.last_error,
            ).where(cond)
        )
    ]
    if rows:
        conn.execute(
            update(_deliveries)
            .where(_deliveries.c.id.in_([r["id"] for r in rows]))
            .values(state="failed", next_attempt_at=now)
        )
    return rows


def pending_count(conn: Connection) -> int:
    """Deliveries not yet delivered nor failed."""
    n: int = conn.execute(
        select(func.count()).select_from(_deliveries).where(_deliveries.c.state == "pending")
    ).scalar_one()
    return n


def undelivered_by_webhook(conn: Connection, *, limit: int) -> dict[str, int]:
    """Per webhook (by name): its events not yet delivered nor failed: its pending deliveries,
    and the events past the fan-out cursor its filters let through (the first `limit` of them;
    the fan-out queues those at every delivery step, so more wait only in a burst)."""
    pending = (
        select(_deliveries.c.webhook_id, func.count().label("n"))
        .where(_deliveries.c.state == "pending")
        .group_by(_deliveries.c.webhook_id)
        .subquery()
    )
    rows = conn.execute(
        select(*PUBLIC_COLUMNS, func.coalesce(pending.c.n, 0).label("n")).join(
            pending, pending.c.webhook_id == _hooks.c.id, isouter=True
        )
    ).all()
    out = {r.name: int(r.n) for r in rows}
    after = read_cursor(conn, WEBHOOKS_CURSOR)
    if after is None:
        return out
    events = [e for e in events_after(conn, after, limit) if not e.muted]
    if events:
        for r in rows:
            hook = dict(r._mapping)
            if hook["enabled"]:
                out[hook["name"]] += sum(1 for e in events if webhook_matches(hook, e))
    return out
