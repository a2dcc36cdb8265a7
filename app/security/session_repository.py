"""Queries of the browser sessions and one-time login codes; each takes a sync Connection."""

from __future__ import annotations

from typing import Any

from sqlalchemy import Connection, delete, insert, select

from eqgw.store.api_models import ApiKey
from eqgw.store.models import table_of
from eqgw.store.security_models import BrowserSession, LoginCode

_sessions = table_of(BrowserSession)
_keys = table_of(ApiKey)
_codes = table_of(LoginCode)


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


def add_login_code(
    conn: Connection, *, code_hash: str, key_id: int, now: float, ttl_s: float
) -> None:
    """Store a one-time login code of `key_id` (expired ones are dropped on the way)."""
    conn.execute(delete(_codes).where(_codes.c.expires_at < now))
    conn.execute(
        insert(_codes).values(
            code_hash=code_hash, key_id=key_id, created_at=now, expires_at=now + ttl_s
        )
    )


def login_code_key(conn: Connection, code_hash: str, now: float) -> dict[str, Any] | None:
    """The key row of an unexpired login code, with the code's `code_expires_at`; the code
    is left as it is (keys revoked included: the caller decides)."""
    row = conn.execute(
        select(_keys, _codes.c.expires_at.label("code_expires_at"))
        .join(_codes, _codes.c.key_id == _keys.c.id)
        .where(_codes.c.code_hash == code_hash, _codes.c.expires_at > now)
    ).first()
    return dict(row._mapping) if row else None


def consume_login_code(conn: Connection, code_hash: str, now: float) -> dict[str, Any] | None:
    """Use a login code up: the key row of the code when it was there and unexpired, else
    None. One statement (DELETE ... RETURNING): of two gateways consuming one code at once,
    one gets it."""
    key_id = conn.execute(
        delete(_codes)
        .where(_codes.c.code_hash == code_hash, _codes.c.expires_at > now)
        .returning(_codes.c.key_id)
    ).scalar()
    if key_id is None:
        return None
    row = conn.execute(select(_keys).where(_keys.c.id == key_id)).first()
    return dict(row._mapping) if row else None
