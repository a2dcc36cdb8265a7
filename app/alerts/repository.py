"""Queries of the alerting tables: rules, alerts with their lifecycle, mutes, alert_events.

Every change of an alert (raised, acknowledged, cleared) appends its `alert_events` row in the
same transaction: that table is the outbox the delivery reads by id, so no change is delivered
without being stored, and none is stored without its event. Each function takes a sync
Connection inside the caller's transaction.
"""

from __future__ import annotations

import datetime as dt
from collections.abc import Sequence
from typing import Any

from sqlalchemy import Connection, and_, delete, insert, or_, select, update
from sqlalchemy.dialects import postgresql, sqlite

from eqgw.store.models import Alert, AlertEvent, AlertMute, AlertRule, Vehicle, table_of

_rules = table_of(AlertRule)
_alerts = table_of(Alert)
_mutes = table_of(AlertMute)
_events = table_of(AlertEvent)
_vehicles = table_of(Vehicle)

ACTIVE, ACKNOWLEDGED, CLEARED = "active", "acknowledged", "cleared"
STATES = (ACTIVE, ACKNOWLEDGED, CLEARED)
RAISED_EVENT, ACK_EVENT, CLEARED_EVENT = "raised", "acknowledged", "cleared"

_ALERT_KEYS = (
    "id",
    "vehicle_id",
    "bus",
    "sa",
    "rule",
    "severity",
    "state",
    "muted",
    "message",
    "values",
    "raised_at",
    "acknowledged_at",
    "acknowledged_by",
    "ack_comment",
    "cleared_at",
    "cleared_by",
)


class AlertStateError(Exception):
    """The alert is not in a state that allows the change (e.g. acknowledging a cleared one)."""


# -- rules --------------------------------------------------------------------------------


def list_rules(conn: Connection) -> list[dict[str, Any]]:
    """Every rule, by id."""
    return [dict(r._mapping) for r in conn.execute(select(_rules).order_by(_rules.c.id))]


def get_rule(conn: Connection, rule_id: str) -> dict[str, Any] | None:
    row = conn.execute(select(_rules).where(_rules.c.id == rule_id)).first()
    return dict(row._mapping) if row else None


def sync_rules(conn: Connection, rules: Sequence[dict[str, Any]], now: float) -> None:
    """Built-in and config-file rules at start: inserted when missing, refreshed unless an
    admin changed them through the API since (source `api`), which then wins."""
    existing = {r["id"]: r for r in list_rules(conn)}
    for rule in rules:
        row = existing.get(rule["id"])
        if row is None:
            conn.execute(insert(_rules).values(**rule, created_at=now, updated_at=now))
        elif row["source"] != "api":
            conn.execute(
                update(_rules).where(_rules.c.id == rule["id"]).values(**rule, updated_at=now)
            )


def insert_rule(conn: Connection, rule: dict[str, Any], now: float) -> bool:
    """A new rule; False when the id is taken."""
    if get_rule(conn, rule["id"]) is not None:
        return False
    conn.execute(insert(_rules).values(**rule, created_at=now, updated_at=now))
    return True


def update_rule(conn: Connection, rule_id: str, values: dict[str, Any], now: float) -> bool:
    result = conn.execute(
        update(_rules).where(_rules.c.id == rule_id).values(**values, updated_at=now)
    )
    return bool(result.rowcount)


def delete_rule(conn: Connection, rule_id: str) -> bool:
    result = conn.execute(delete(_rules).where(_rules.c.id == rule_id))
    return bool(result.rowcount)


# -- alerts -------------------------------------------------------------------------------


def _vehicle_name(conn: Connection, vehicle_id: str) -> str:
    name = conn.execute(select(_vehicles.c.name).where(_vehicles.c.id == vehicle_id)).scalar()
    return str(name) if name else vehicle_id


def alert_dict(row: Any, vehicle_name: str | None = None) -> dict[str, Any]:
    """An alert as the API, the hub and the event payload show it (times: epoch floats)."""
    m = row._mapping if hasattr(row, "_mapping") else row
    out = {k: m[k] for k in _ALERT_KEYS}
    out["muted"] = bool(out["muted"])
    out["vehicle_name"] = vehicle_name or m.get("vehicle_name") or m["vehicle_id"]
    return out


def _append_event(conn: Connection, alert: dict[str, Any], kind: str, ts: float) -> int:
    payload = {"event": kind, "ts": ts, "alert": alert}
    result = conn.execute(
        insert(_events)
        .values(alert_id=alert["id"], kind=kind, ts=ts, payload=payload, muted=alert["muted"])
        .returning(_events.c.id)
    )
    event_id: int = result.scalar_one()
    return event_id


def _insert_open(conn: Connection, values: dict[str, Any]) -> int | None:
    """Insert an open alert; None when (bus, sa, rule) already has one (the partial unique
    index decides, so concurrent raisers in any process yield one alert)."""
    ins = postgresql.insert if conn.dialect.name == "postgresql" else sqlite.insert
    stmt = (
        ins(_alerts)
        .values(**values)
        .on_conflict_do_nothing(
            index_elements=["bus", "sa", "rule"], index_where=_alerts.c.cleared_at.is_(None)
        )
        .returning(_alerts.c.id)
    )
    alert_id: int | None = conn.execute(stmt).scalar()
    return alert_id


def open_alert_of(conn: Connection, bus: str, sa: int, rule: str) -> dict[str, Any] | None:
    row = conn.execute(
        select(_alerts).where(
            _alerts.c.bus == bus,
            _alerts.c.sa == sa,
            _alerts.c.rule == rule,
            _alerts.c.cleared_at.is_(None),
        )
    ).first()
    return alert_dict(row) if row else None


def raise_alert(
    conn: Connection,
    *,
    vehicle_id: str,
    bus: str,
    sa: int,
    rule: str,
    severity: str,
    message: str,
    values: dict[str, Any],
    ts: float,
    muted: bool,
) -> tuple[dict[str, Any], bool]:
    """Open an alert and append its `raised` event; returns (alert, True), or the alert
    already open for (unit, rule) and False (nothing written)."""
    alert_id = _insert_open(
        conn,
        {
            "vehicle_id": vehicle_id,
            "bus": bus,
            "sa": sa,
            "rule": rule,
            "severity": severity,
            "state": ACTIVE,
            "muted": muted,
            "message": message[:2000],
            "values": values,
            "raised_at": ts,
            "updated_at": ts,
        },
    )
    if alert_id is None:
        existing = open_alert_of(conn, bus, sa, rule)
        if existing is None:  # cleared between the two statements: try once more
            return raise_alert(
                conn,
                vehicle_id=vehicle_id,
                bus=bus,
                sa=sa,
                rule=rule,
                severity=severity,
                message=message,
                values=values,
                ts=ts,
                muted=muted,
            )
        return existing, False
    alert = get_alert(conn, alert_id)
    assert alert is not None
    _append_event(conn, alert, RAISED_EVENT, ts)
    return alert, True


def acknowledge_alert(
    conn: Connection, alert_id: int, *, by: str, comment: str | None, ts: float
) -> dict[str, Any] | None:
    """Acknowledge an active alert and append the event; None when there is no such alert;
    AlertStateError when it is already acknowledged or cleared."""
    result = conn.execute(
        update(_alerts)
        .where(_alerts.c.id == alert_id, _alerts.c.state == ACTIVE)
        .values(
            state=ACKNOWLEDGED,
            acknowledged_at=ts,
            acknowledged_by=by,
            ack_comment=comment,
            updated_at=ts,
        )
    )
    alert = get_alert(conn, alert_id)
    if alert is None:
        return None
    if not result.rowcount:
        raise AlertStateError(
            f"alert {alert_id} is {alert['state']}; only active alerts can be acknowledged"
        )
    _append_event(conn, alert, ACK_EVENT, ts)
    return alert


def clear_alert(conn: Connection, alert_id: int, *, ts: float, by: str) -> dict[str, Any] | None:
    """Clear an open alert (acknowledged or not) and append the event; None when it is not
    open (already cleared, or unknown)."""
    result = conn.execute(
        update(_alerts)
        .where(_alerts.c.id == alert_id, _alerts.c.cleared_at.is_(None))
        .values(state=CLEARED, cleared_at=ts, cleared_by=by, updated_at=ts)
    )
    if not result.rowcount:
        return None
    alert = get_alert(conn, alert_id)
    assert alert is not None
    _append_event(conn, alert, CLEARED_EVENT, ts)
    return alert


def get_alert(conn: Connection, alert_id: int) -> dict[str, Any] | None:
    row = conn.execute(
        select(_alerts, _vehicles.c.name.label("vehicle_name"))
        .outerjoin(_vehicles, _vehicles.c.id == _alerts.c.vehicle_id)
        .where(_alerts.c.id == alert_id)
    ).first()
    return alert_dict(row) if row else None


def open_alerts(conn: Connection) -> list[dict[str, Any]]:
    """Every alert not cleared (for the engine at start)."""
    rows = conn.execute(select(_alerts).where(_alerts.c.cleared_at.is_(None)))
    return [alert_dict(r) for r in rows]


def list_alerts(
    conn: Connection,
    *,
    vehicle_id: str | None = None,
    states: Sequence[str] | None = None,
    severities: Sequence[str] | None = None,
    rules: Sequence[str] | None = None,
    start: float | None = None,
    end: float | None = None,
    muted: bool | None = None,
    limit: int = 100,
    before_id: int | None = None,
    vehicle_ids: Sequence[str] | None = None,
    after_id: int | None = None,
) -> list[dict[str, Any]]:
    """Alerts newest first; `start`/`end` select alerts open at some time in the range;
    with `vehicle_ids` (a key's scope) only theirs. With `after_id`, a page of an export
    instead: those of id above it, oldest first."""
    stmt = select(_alerts, _vehicles.c.name.label("vehicle_name")).outerjoin(
        _vehicles, _vehicles.c.id == _alerts.c.vehicle_id
    )
    if vehicle_ids is not None:
        stmt = stmt.where(_alerts.c.vehicle_id.in_(list(vehicle_ids)))
    if vehicle_id is not None:
        stmt = stmt.where(_alerts.c.vehicle_id == vehicle_id)
    if states:
        stmt = stmt.where(_alerts.c.state.in_(states))
    if severities:
        stmt = stmt.where(_alerts.c.severity.in_(severities))
    if rules:
        stmt = stmt.where(_alerts.c.rule.in_(rules))
    if end is not None:
        stmt = stmt.where(_alerts.c.raised_at <= end)
    if start is not None:
        stmt = stmt.where(or_(_alerts.c.cleared_at.is_(None), _alerts.c.cleared_at >= start))
    if muted is not None:
        stmt = stmt.where(_alerts.c.muted.is_(muted))
    if before_id is not None:
        stmt = stmt.where(_alerts.c.id < before_id)
    if after_id is not None:
        stmt = stmt.where(_alerts.c.id > after_id).order_by(_alerts.c.id).limit(limit)
    else:
        stmt = stmt.order_by(_alerts.c.id.desc()).limit(limit)
    return [alert_dict(r) for r in conn.execute(stmt)]


def alert_events(conn: Connection, alert_id: int) -> list[dict[str, Any]]:
    """The changes of one alert, oldest first."""
    rows = conn.execute(
        select(_events).where(_events.c.alert_id == alert_id).order_by(_events.c.id)
    )
    return [{**dict(r._mapping), "muted": bool(r.muted)} for r in rows]


def events_after(conn: Connection, after_id: int, limit: int = 500) -> list[dict[str, Any]]:
    """alert_events rows with id > after_id, in id order (the delivery cursor)."""
    rows = conn.execute(
        select(_events).where(_events.c.id > after_id).order_by(_events.c.id).limit(limit)
    )
    return [{**dict(r._mapping), "muted": bool(r.muted)} for r in rows]


# -- mutes --------------------------------------------------------------------------------


def insert_mute(conn: Connection, mute: dict[str, Any], now: float) -> dict[str, Any]:
    mute_id = conn.execute(
        insert(_mutes).values(**mute, created_at=now).returning(_mutes.c.id)
    ).scalar_one()
    row = get_mute(conn, mute_id)
    assert row is not None
    return row


def get_mute(conn: Connection, mute_id: int) -> dict[str, Any] | None:
    row = conn.execute(select(_mutes).where(_mutes.c.id == mute_id)).first()
    return dict(row._mapping) if row else None


def list_mutes(
    conn: Connection, *, active_at: float | None = None, vehicle_ids: Sequence[str] | None = None
) -> list[dict[str, Any]]:
    """Mutes, newest first; with `active_at`, only those not cancelled and not expired then;
    with `vehicle_ids` (a key's scope) only the mutes of those vehicles and fleet-wide ones."""
    stmt = select(_mutes)
    if vehicle_ids is not None:
        m = _mutes.c
        stmt = stmt.where(or_(m.vehicle_id.is_(None), m.vehicle_id.in_(list(vehicle_ids))))
    if active_at is not None:
        stmt = stmt.where(_mutes.c.cancelled_at.is_(None), _mutes.c.ends_at > active_at)
    return [dict(r._mapping) for r in conn.execute(stmt.order_by(_mutes.c.id.desc()))]


def cancel_mute(conn: Connection, mute_id: int, now: float) -> bool:
    result = conn.execute(
        update(_mutes)
        .where(_mutes.c.id == mute_id, _mutes.c.cancelled_at.is_(None))
        .values(cancelled_at=now)
    )
    return bool(result.rowcount)


def mute_covers(mute: dict[str, Any], vehicle_id: str, rule: str, now: float) -> bool:
    """Whether a mute applies to this vehicle and rule at `now` (epoch s, UTC quiet hours)."""
    if mute.get("cancelled_at") is not None:
        return False
    if not mute["starts_at"] <= now < mute["ends_at"]:
        return False
    if mute["vehicle_id"] not in (None, vehicle_id) or mute["rule"] not in (None, rule):
        return False
    lo, hi = mute.get("daily_from_min"), mute.get("daily_to_min")
    if lo is None or hi is None:
        return True
    t = dt.datetime.fromtimestamp(now, dt.UTC)
    minute = t.hour * 60 + t.minute
    return bool(lo <= minute < hi) if lo <= hi else bool(minute >= lo or minute < hi)


def is_muted(conn: Connection, vehicle_id: str, rule: str, now: float) -> bool:
    """Whether any mute covers this vehicle and rule at `now`."""
    rows = conn.execute(
        select(_mutes).where(
            _mutes.c.cancelled_at.is_(None),
            _mutes.c.starts_at <= now,
            _mutes.c.ends_at > now,
            and_(
                or_(_mutes.c.vehicle_id.is_(None), _mutes.c.vehicle_id == vehicle_id),
                or_(_mutes.c.rule.is_(None), _mutes.c.rule == rule),
            ),
        )
    )
    return any(mute_covers(dict(r._mapping), vehicle_id, rule, now) for r in rows)
