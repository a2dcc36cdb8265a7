"""Queries of the browser sessions; each takes a sync Connection."""

from __future__ import annotations

from typing import Any

from sqlalchemy import Connection, Table, delete, insert, select

from eqgw.store.api_models import ApiKey
from eqgw.store.security_models import BrowserSession

_sessions: Table = BrowserSession.__table__  # type: ignore[assignment]
_keys: Table = ApiKey.__table__  # type: ignore[assignment]


def create_session(
    conn: Connection, *, token_hash: str, key_id: int, csrf_token: str, now: float, ttl_s: float
) -> None:
    """Store a new session of `key_id` (expired ones are dropped on the way)."""
    conn.execute(delete(_sessions).where(_sessions.c.expires_at < now))
    conn.execute(
        insert(_sessions).values(
            token_hash=token_hash,
            key_id=key_id,
            csrf_token=csrf_token,
            created_at=now,
            expires_at=now + ttl_s,
        )
    )


def session_key(conn: Connection, token_hash: str, now: float) -> dict[str, Any] | None:
    """The key row of an unexpired session (keys revoked included: the caller decides), with
    the session's `csrf_token` and `session_expires_at`."""
    row = conn.execute(
        select(
            _keys,
            _sessions.c.csrf_token,
            _sessions.c.expires_at.label("session_expires_at"),
        )
        .join(_sessions, _sessions.c.key_id == _keys.c.id)
        .where(_sessions.c.token_hash == token_hash, _sessions.c.expires_at > now)
    ).first()
    return dict(row._mapping) if row else None


def delete_session(conn: Connection, token_hash: str) -> bool:
    """End a session (logout); False when there was none."""
    return bool(
        conn.execute(delete(_sessions).where(_sessions.c.token_hash == token_hash)).rowcount
    )
