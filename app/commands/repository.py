"""Queries of the command queue; each takes a sync Connection."""

from __future__ import annotations

from collections.abc import Callable, Iterable

from sqlalchemy import Connection, insert, select, text, update

from eqgw.commands.model import PENDING_STATES, Command, CommandChanges, CommandState
from eqgw.store import api_models
from eqgw.store.models import table_of

_commands = table_of(api_models.Command)


# -- commands -----------------------------------------------------------------------------


def insert_command(conn: Connection, cmd: Command) -> None:
    """Queue a command."""
    conn.execute(insert(_commands).values(**cmd.to_row()))


def get_command(conn: Connection, command_id: str) -> Command | None:
    """One command by id."""
    row = conn.execute(select(_commands).where(_commands.c.id == command_id)).first()
    return Command.from_row(row._mapping) if row else None


def ended_commands(conn: Connection, ids: Iterable[str]) -> dict[str, CommandChanges]:
    """Of these commands, the ones that have ended: id -> {state, reason}."""
    c = _commands.c
    stmt = select(c.id, c.state, c.reason).where(
        c.id.in_(list(ids)), c.state.not_in(PENDING_STATES)
    )
    return {r.id: {"state": r.state, "reason": r.reason} for r in conn.execute(stmt)}


def command_by_idempotency(conn: Connection, key_id: int, idem: str) -> Command | None:
    """The command a key already created with this Idempotency-Key."""
    c = _commands.c
    row = conn.execute(
        select(_commands).where(c.key_id == key_id, c.idempotency_key == idem)
    ).first()
    return Command.from_row(row._mapping) if row else None


def list_commands(
    conn: Connection,
    *,
    vehicle_id: str | None = None,
    states: Iterable[str] | None = None,
    vehicle_ids: Iterable[str] | None = None,
    limit: int = 100,
) -> list[Command]:
    """Commands, newest first; with `vehicle_ids` (a key's scope) only theirs."""
    c = _commands.c
    stmt = select(_commands).order_by(c.created_at.desc(), c.id).limit(limit)
    if vehicle_ids is not None:
        stmt = stmt.where(c.vehicle_id.in_(list(vehicle_ids)))
    if vehicle_id is not None:
        stmt = stmt.where(c.vehicle_id == vehicle_id)
    if states is not None:
        stmt = stmt.where(c.state.in_(list(states)))
    return [Command.from_row(r._mapping) for r in conn.execute(stmt)]


def pending_commands(
    conn: Connection, buses: Iterable[str], *, unexpired_at: float | None = None
) -> list[Command]:
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
    return [Command.from_row(r._mapping) for r in conn.execute(stmt)]


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
    conn: Connection, command_id: str, values: CommandChanges, *, only_pending: bool = True
) -> bool:
    """Change a command; with `only_pending`, never touch one that already ended."""
    stmt = update(_commands).where(_commands.c.id == command_id).values(**values)
    if only_pending:
        stmt = stmt.where(_commands.c.state.in_(PENDING_STATES))
    return bool(conn.execute(stmt).rowcount)


# How a command ends, decided from its row as it is when it ends: (final state, reason).
Decide = Callable[[Command], tuple[CommandState, str]]


def end_command(conn: Connection, command_id: str, decide: Decide, now: float) -> Command | None:
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
    cmd = Command.from_row(row._mapping)
    state, reason = decide(cmd)
    values: CommandChanges = {"state": state, "reason": reason, "updated_at": now}
    conn.execute(update(_commands).where(c.id == command_id).values(**values))
    cmd.apply(values)
    return cmd


def add_frames_handed(conn: Connection, command_id: str, frames: int) -> None:
    """Count frames handed over in a send that did not complete."""
    c = _commands.c
    conn.execute(
        update(_commands).where(c.id == command_id).values(frames_handed=c.frames_handed + frames)
    )


def end_unowned(
    conn: Connection, skip_buses: Iterable[str], before: float, decide: Decide, now: float
) -> list[Command]:
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
