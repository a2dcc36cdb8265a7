"""Queries of the browser sessions, one-time login codes and single sign-on people; each
takes a sync Connection."""

from __future__ import annotations

from typing import Any

from sqlalchemy import Connection, delete, insert, select, update

from eqgw.store.api_models import ApiKey
from eqgw.store.models import table_of
from eqgw.store.security_models import BrowserSession, LoginCode, SsoPerson

_sessions = table_of(BrowserSession)
_keys = table_of(ApiKey)
_codes = table_of(LoginCode)
_people = table_of(SsoPerson)


def create_session(
    conn: Connection,
    *,
    token_hash: str,
    key_id: int,
    csrf_token: str,
    now: float,
    ttl_s: float,
    person_id: int | None = None,
    grants: list[dict[str, Any]] | None = None,
) -> None:
    """Store a new session of `key_id` (a person's, with the grants of their sign-in);
    expired ones are dropped on the way."""
    conn.execute(delete(_sessions).where(_sessions.c.expires_at < now))
    conn.execute(
        insert(_sessions).values(
            token_hash=token_hash,
            key_id=key_id,
            csrf_token=csrf_token,
            created_at=now,
            expires_at=now + ttl_s,
            person_id=person_id,
            grants=grants,
        )
    )


def session_key(conn: Connection, token_hash: str, now: float) -> dict[str, Any] | None:
    """The key row of an unexpired session (keys revoked included: the caller decides), with
    the session's `csrf_token`, `session_expires_at` and `grants`, and its person's
    `person_subject` and `person_email` (None for a key's session)."""
    row = conn.execute(
        select(
            _keys,
            _sessions.c.csrf_token,
            _sessions.c.expires_at.label("session_expires_at"),
            _sessions.c.grants,
            _people.c.subject.label("person_subject"),
            _people.c.email.label("person_email"),
        )
        .join(_sessions, _sessions.c.key_id == _keys.c.id)
        .outerjoin(_people, _people.c.id == _sessions.c.person_id)
        .where(_sessions.c.token_hash == token_hash, _sessions.c.expires_at > now)
    ).first()
    return dict(row._mapping) if row else None


def person_key(
    conn: Connection,
    *,
    issuer: str,
    subject: str,
    email: str | None,
    name: str | None,
    key: dict[str, Any],
    now: float,
) -> tuple[int, int]:
    """The person `issuer`/`subject` after a sign-in: (person id, id of their key row). Their
    email and name are updated, and their key row's name, role and scope (`key`: the values
    of a new key row); a person seen first, or whose key row was revoked, gets a new key row
    (then of the old one's lineage). Call in a transaction that writes first (SQLite)."""
    person = (
        conn.execute(
            select(_people).where(_people.c.issuer == issuer, _people.c.subject == subject)
        )
        .mappings()
        .first()
    )
    old = None
    if person is not None:
        old = conn.execute(select(_keys).where(_keys.c.id == person["key_id"])).mappings().first()
    listed = {k: key[k] for k in ("name", "role", "scope_groups", "scope_vehicles")}
    if old is not None and (old["revoked_at"] is None or old["revoked_at"] > now):
        key_id = int(old["id"])
        conn.execute(update(_keys).where(_keys.c.id == key_id).values(**listed))
    else:
        lineage = (old["lineage"] or old["id"]) if old is not None else None
        key_id = int(
            conn.execute(
                insert(_keys).values(**key, created_at=now, lineage=lineage).returning(_keys.c.id)
            ).scalar_one()
        )
    seen = {"email": email, "name": name, "key_id": key_id, "last_login_at": now}
    if person is None:
        person_id = int(
            conn.execute(
                insert(_people)
                .values(issuer=issuer, subject=subject, created_at=now, **seen)
                .returning(_people.c.id)
            ).scalar_one()
        )
    else:
        person_id = int(person["id"])
        conn.execute(update(_people).where(_people.c.id == person_id).values(**seen))
    return person_id, key_id


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
