"""Queries of the API's tables (keys, audit log, commands); each takes a sync Connection."""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any

from sqlalchemy import Connection, Table, func, insert, select, update

from app.store.api_models import ApiKey, AuditEntry, Command

_keys: Table = ApiKey.__table__  # type: ignore[assignment]
_audit: Table = AuditEntry.__table__  # type: ignore[assignment]
_commands: Table = Command.__table__  # type: ignore[assignment]

# Commands in these states may still reach the bus.
PENDING_STATES = ("queued", "sending")


# -- keys ---------------------------------------------------------------------------------


def insert_key(
    conn: Connection, *, name: str, role: str, prefix: str, key_hash: str, now: float
) -> int:
    """Store a new key; returns its id."""
    result = conn.execute(
        insert(_keys)
        .values(name=name, role=role, prefix=prefix, key_hash=key_hash, created_at=now)
        .returning(_keys.c.id)
    )
    key_id: int = result.scalar_one()
    return key_id


def key_by_hash(conn: Connection, key_hash: str) -> dict[str, Any] | None:
    """The key with this hash (revoked ones included: the caller decides)."""
    row = conn.execute(select(_keys).where(_keys.c.key_hash == key_hash)).first()
    return dict(row._mapping) if row else None


def list_keys(conn: Connection) -> list[dict[str, Any]]:
    """Every key, without its hash."""
    cols = [c for c in _keys.c if c.name != "key_hash"]
    return [dict(r._mapping) for r in conn.execute(select(*cols).order_by(_keys.c.id))]


def revoke_key(conn: Connection, key_id: int, now: float) -> bool:
    """Revoke a key; False when there is no such key or it was already revoked."""
    result = conn.execute(
        update(_keys)
        .where(_keys.c.id == key_id, _keys.c.revoked_at.is_(None))
        .values(revoked_at=now)
    )
    return bool(result.rowcount)


def count_active_keys(conn: Connection, role: str | None = None) -> int:
    """Keys not revoked (of one role, if given)."""
    stmt = select(func.count()).select_from(_keys).where(_keys.c.revoked_at.is_(None))
    if role is not None:
        stmt = stmt.where(_keys.c.role == role)
    n: int = conn.execute(stmt).scalar_one()
    return n


def count_keys(conn: Connection) -> int:
    """Keys ever created (revoked ones too): zero means a first start."""
    n: int = conn.execute(select(func.count()).select_from(_keys)).scalar_one()
    return n


def touch_keys(conn: Connection, last_used: dict[int, float]) -> None:
    """Record when keys were last used (batched by the caller)."""
    for key_id, ts in last_used.items():
        conn.execute(update(_keys).where(_keys.c.id == key_id).values(last_used_at=ts))


# -- audit --------------------------------------------------------------------------------


def add_audit(conn: Connection, entry: dict[str, Any]) -> None:
    """Append one audit entry."""
    conn.execute(insert(_audit).values(**entry))


def list_audit(
    conn: Connection,
    *,
    start: float | None = None,
    end: float | None = None,
    vehicle_id: str | None = None,
    key_id: int | None = None,
    limit: int = 100,
) -> list[dict[str, Any]]:
    """Audit entries, newest first."""
    a = _audit.c
    stmt = select(_audit).order_by(a.ts.desc(), a.id.desc()).limit(limit)
    if start is not None:
        stmt = stmt.where(a.ts >= start)
    if end is not None:
        stmt = stmt.where(a.ts < end)
    if vehicle_id is not None:
        stmt = stmt.where(a.vehicle_id == vehicle_id)
    if key_id is not None:
        stmt = stmt.where(a.key_id == key_id)
    return [dict(r._mapping) for r in conn.execute(stmt)]


# -- commands -----------------------------------------------------------------------------


def insert_command(conn: Connection, row: dict[str, Any]) -> None:
    """Queue a command."""
    conn.execute(insert(_commands).values(**row))


def get_command(conn: Connection, command_id: str) -> dict[str, Any] | None:
    """One command by id."""
    row = conn.execute(select(_commands).where(_commands.c.id == command_id)).first()
    return dict(row._mapping) if row else None


def ended_commands(conn: Connection, ids: Iterable[str]) -> dict[str, dict[str, Any]]:
    """Of these commands, the ones that have ended: id -> {state, reason}."""
    c = _commands.c
    stmt = select(c.id, c.state, c.reason).where(
        c.id.in_(list(ids)), c.state.not_in(PENDING_STATES)
    )
    return {r.id: {"state": r.state, "reason": r.reason} for r in conn.execute(stmt)}


def command_by_idempotency(conn: Connection, key_id: int, idem: str) -> dict[str, Any] | None:
    """The command a key already created with this Idempotency-Key."""
    c = _commands.c
    row = conn.execute(
        select(_commands).where(c.key_id == key_id, c.idempotency_key == idem)
    ).first()
    return dict(row._mapping) if row else None


def list_commands(
    conn: Connection,
    *,
    vehicle_id: str | None = None,
    states: Iterable[str] | None = None,
    limit: int = 100,
) -> list[dict[str, Any]]:
    """Commands, newest first."""
    c = _commands.c
    stmt = select(_commands).order_by(c.created_at.desc(), c.id).limit(limit)
    if vehicle_id is not None:
        stmt = stmt.where(c.vehicle_id == vehicle_id)
    if states is not None:
        stmt = stmt.where(c.state.in_(list(states)))
    return [dict(r._mapping) for r in conn.execute(stmt)]


def pending_commands(conn: Connection, buses: Iterable[str]) -> list[dict[str, Any]]:
    """Commands still to deliver on these buses, oldest first."""
    c = _commands.c
    stmt = (
        select(_commands)
        .where(c.state.in_(PENDING_STATES), c.bus.in_(list(buses)))
        .order_by(c.created_at, c.id)
    )
    return [dict(r._mapping) for r in conn.execute(stmt)]


def update_command(
    conn: Connection, command_id: str, values: dict[str, Any], *, only_pending: bool = True
) -> bool:
    """Change a command; with `only_pending`, never touch one that already ended."""
    stmt = update(_commands).where(_commands.c.id == command_id).values(**values)
    if only_pending:
        stmt = stmt.where(_commands.c.state.in_(PENDING_STATES))
    return bool(conn.execute(stmt).rowcount)


def expire_unsent(conn: Connection, skip_buses: Iterable[str], now: float) -> list[dict[str, Any]]:
    """End, as expired, the commands whose expiry is at or before `now` that were never sent,
    on buses other than `skip_buses` (those a caller delivers on itself); returns them.

    A command for a bus no running gateway reads would otherwise stay queued forever. Only
    rows still queued with no send are touched, in one conditional UPDATE each, so a frame
    another gateway sent just before the expiry is never reported as unsent.
    """
    c = _commands.c
    stmt = select(_commands).where(c.state == "queued", c.sends == 0, c.expires_at <= now)
    skip = list(skip_buses)
    if skip:
        stmt = stmt.where(c.bus.not_in(skip))
    ended = []
    for row in conn.execute(stmt).all():
        cmd = dict(row._mapping)
        reason = f"expired before it could be sent: no gateway delivered on {cmd['bus']}"
        values = {"state": "expired", "reason": reason, "updated_at": now}
        done = conn.execute(
            update(_commands)
            .where(c.id == cmd["id"], c.state == "queued", c.sends == 0)
            .values(**values)
        ).rowcount
        if done:
            cmd.update(values)
            ended.append(cmd)
    return ended


def command_outcomes(conn: Connection) -> dict[str, int]:
    """Number of commands per state (for /metrics)."""
    c = _commands.c
    rows = conn.execute(select(c.state, func.count()).group_by(c.state)).all()
    return {row[0]: row[1] for row in rows}
