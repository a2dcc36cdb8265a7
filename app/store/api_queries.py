"""Queries of the API's tables (keys, audit log, commands); each takes a sync Connection."""

from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping
from typing import Any

from sqlalchemy import Connection, Table, delete, func, insert, or_, select, text, update

from eqgw.store.api_models import ApiKey, AuditEntry, Command

_keys: Table = ApiKey.__table__  # type: ignore[assignment]
_audit: Table = AuditEntry.__table__  # type: ignore[assignment]
_commands: Table = Command.__table__  # type: ignore[assignment]

# Commands in these states may still reach the bus.
PENDING_STATES = ("queued", "sending")


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
    vehicle_ids: Iterable[str] | None = None,
    limit: int = 100,
) -> list[dict[str, Any]]:
    """Commands, newest first; with `vehicle_ids` (a key's scope) only theirs."""
    c = _commands.c
    stmt = select(_commands).order_by(c.created_at.desc(), c.id).limit(limit)
    if vehicle_ids is not None:
        stmt = stmt.where(c.vehicle_id.in_(list(vehicle_ids)))
    if vehicle_id is not None:
        stmt = stmt.where(c.vehicle_id == vehicle_id)
    if states is not None:
        stmt = stmt.where(c.state.in_(list(states)))
    return [dict(r._mapping) for r in conn.execute(stmt)]


def pending_commands(
    conn: Connection, buses: Iterable[str], *, unexpired_at: float | None = None
) -> list[dict[str, Any]]:
    """Commands still to deliver on these buses, oldest first; with `unexpired_at`, only
    those whose expiry is later (a command past it is never sent again)."""
    c = _commands.c
    stmt = (
        select(_commands)
        .where(c.state.in_(PENDING_STATES), c.bus.in_(list(buses)))
        .order_by(c.created_at, c.id)
    )
    if unexpired_at is not None:
        stmt = stmt.where(c.expires_at > unexpired_at)
    return [dict(r._mapping) for r in conn.execute(stmt)]


def lock_command_queue(conn: Connection, bus: str, idempotency: tuple[int, str] | None) -> None:
    """Hold, until the transaction ends, the lock that serializes queueing commands for `bus`
    (and, first, the one of a key's Idempotency-Key) across every process on the database.

    PostgreSQL: transaction-level advisory locks keyed by a hash of the database, the schema
    and the name, so deployments in other schemas of one server never wait on each other (a
    hash collision only makes two queues wait in turn). SQLite: the caller's transaction
    already holds the database's write lock from its start (BEGIN IMMEDIATE)."""
    if conn.dialect.name != "postgresql":
        return
    names = [] if idempotency is None else [f"idempotency:{idempotency[0]}:{idempotency[1]}"]
    names.append(f"bus:{bus}")
    for name in names:  # always in this order, so no two submissions deadlock
        conn.execute(
            text(
                "SELECT pg_advisory_xact_lock(hashtextextended("
                "'eqgw-commands/' || current_database() || '/' || current_schema() || '/' "
                "|| :name, 0))"
            ),
            {"name": name},
        )


def update_command(
    conn: Connection, command_id: str, values: dict[str, Any], *, only_pending: bool = True
) -> bool:
    """Change a command; with `only_pending`, never touch one that already ended."""
    stmt = update(_commands).where(_commands.c.id == command_id).values(**values)
    if only_pending:
        stmt = stmt.where(_commands.c.state.in_(PENDING_STATES))
    return bool(conn.execute(stmt).rowcount)


Decide = Callable[[Mapping[str, Any]], tuple[str, str]]


def end_command(
    conn: Connection, command_id: str, decide: Decide, now: float
) -> dict[str, Any] | None:
    """End a pending command in the state and with the reason `decide(row)` gives from the
    row as it is now (locked: a hand-over recorded concurrently is seen); the ended row, or
    None when the command was not pending. Run it where the write lock is held from the
    start on SQLite (a serialized transaction)."""
    c = _commands.c
    row = conn.execute(
        select(_commands).where(c.id == command_id, c.state.in_(PENDING_STATES)).with_for_update()
    ).first()
    if row is None:
        return None
    cmd = dict(row._mapping)
    state, reason = decide(cmd)
    values = {"state": state, "reason": reason, "updated_at": now}
    conn.execute(update(_commands).where(c.id == command_id).values(**values))
    cmd.update(values)
    return cmd


def add_frames_handed(conn: Connection, command_id: str, frames: int) -> None:
    """Count frames handed over in a send that did not complete."""
    c = _commands.c
    conn.execute(
        update(_commands).where(c.id == command_id).values(frames_handed=c.frames_handed + frames)
    )


def end_unowned(
    conn: Connection, skip_buses: Iterable[str], before: float, decide: Decide, now: float
) -> list[dict[str, Any]]:
    """End the pending commands whose expiry is at or before `before`, on buses other than
    `skip_buses` (those a caller delivers on itself), as `decide(row)` says; returns them.

    A command for a bus no running gateway reads would otherwise stay pending forever. Each
    one is ended from its locked row, so a frame another gateway handed over just before is
    seen by `decide`.
    """
    c = _commands.c
    stmt = select(c.id).where(c.state.in_(PENDING_STATES), c.expires_at <= before)
    skip = list(skip_buses)
    if skip:
        stmt = stmt.where(c.bus.not_in(skip))
    ended = []
    for (command_id,) in conn.execute(stmt).all():
        cmd = end_command(conn, command_id, decide, now)
        if cmd is not None:
            ended.append(cmd)
    return ended
