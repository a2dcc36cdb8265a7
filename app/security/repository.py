"""Queries of the API keys and the audit log; each takes a sync Connection."""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any

from sqlalchemy import Connection, delete, func, insert, or_, select, update

from eqgw.store.api_models import ApiKey, AuditEntry
from eqgw.store.models import table_of

_keys = table_of(ApiKey)
_audit = table_of(AuditEntry)

# -- keys ---------------------------------------------------------------------------------


def insert_key(
    conn: Connection,
    *,
    name: str,
    role: str,
    prefix: str,
    key_hash: str,
    now: float,
    scope_groups: list[str] | None = None,
    scope_vehicles: list[str] | None = None,
    expires_at: float | None = None,
    lineage: int | None = None,
) -> int:
    """Store a new key; returns its id."""
    result = conn.execute(
        insert(_keys)
        .values(
            name=name,
            role=role,
            prefix=prefix,
            key_hash=key_hash,
            created_at=now,
            scope_groups=scope_groups,
            scope_vehicles=scope_vehicles,
            expires_at=expires_at,
            lineage=lineage,
        )
        .returning(_keys.c.id)
    )
    key_id: int = result.scalar_one()
    return key_id


def key_by_hash(conn: Connection, key_hash: str) -> dict[str, Any] | None:
    """The key with this hash (revoked ones included: the caller decides)."""
    row = conn.execute(select(_keys).where(_keys.c.key_hash == key_hash)).first()
    return dict(row._mapping) if row else None


def get_key(conn: Connection, key_id: int) -> dict[str, Any] | None:
    """One key by id, without its hash."""
    cols = [c for c in _keys.c if c.name != "key_hash"]
    row = conn.execute(select(*cols).where(_keys.c.id == key_id)).first()
    return dict(row._mapping) if row else None


def list_keys(conn: Connection) -> list[dict[str, Any]]:
    """Every key, without its hash."""
    cols = [c for c in _keys.c if c.name != "key_hash"]
    return [dict(r._mapping) for r in conn.execute(select(*cols).order_by(_keys.c.id))]


def revoke_key(conn: Connection, key_id: int, now: float) -> bool:
    """Revoke a key from `now` on; False when there is no such key or it was already revoked
    by then (a key in a rotation's overlap, revoked later, is revoked at `now`)."""
    k = _keys.c
    result = conn.execute(
        update(_keys)
        .where(k.id == key_id, or_(k.revoked_at.is_(None), k.revoked_at > now))
        .values(revoked_at=now)
    )
    return bool(result.rowcount)


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
    vehicle_ids: Iterable[str] | None = None,
    limit: int = 100,
    after_id: int | None = None,
) -> list[dict[str, Any]]:
    """Audit entries, newest first; with `vehicle_ids` (a key's scope) only theirs. With
    `after_id`, a page of an export instead: those of id above it, in id order."""
    a = _audit.c
    if after_id is not None:
        stmt = select(_audit).where(a.id > after_id).order_by(a.id).limit(limit)
    else:
        stmt = select(_audit).order_by(a.ts.desc(), a.id.desc()).limit(limit)
    if vehicle_ids is not None:
        stmt = stmt.where(a.vehicle_id.in_(list(vehicle_ids)))
    if start is not None:
        stmt = stmt.where(a.ts >= start)
    if end is not None:
        stmt = stmt.where(a.ts < end)
    if vehicle_id is not None:
        stmt = stmt.where(a.vehicle_id == vehicle_id)
    if key_id is not None:
        stmt = stmt.where(a.key_id == key_id)
    return [dict(r._mapping) for r in conn.execute(stmt)]


def prune_audit(conn: Connection, before: float, limit: int = 5000) -> int:
    """Delete up to `limit` audit entries older than `before` (oldest first); returns how
    many (the caller repeats, one short transaction each, until fewer than `limit`)."""
    a = _audit.c
    ids = select(a.id).where(a.ts < before).order_by(a.ts).limit(limit).scalar_subquery()
    return int(conn.execute(delete(_audit).where(a.id.in_(ids))).rowcount)
