"""API keys and roles: generation, hashing, cached lookup, and the FastAPI dependencies."""

from __future__ import annotations

import hashlib
import secrets
import time
from dataclasses import dataclass
from typing import Any

from sqlalchemy import Engine

from app.store import api_queries as q

# Ranked roles: each includes the ones before it.
RANKED_ROLES = ("viewer", "operator", "admin")
# `ingest` (edge forwarders posting frames) stands apart: it satisfies only itself, and no
# other role satisfies it, so a vehicle's key can never read the fleet and a reader's key
# can never write history.
INGEST = "ingest"
ROLES = (*RANKED_ROLES, INGEST)
_RANK = {role: i for i, role in enumerate(RANKED_ROLES)}
KEY_PREFIX = "eqgw_"


@dataclass(frozen=True, slots=True)
class Principal:
    """The key a request was made with."""

    key_id: int
    name: str
    role: str

    def allows(self, role: str) -> bool:
        """Whether this key's role includes `role` (admin > operator > viewer; ingest alone)."""
        if role == INGEST or self.role == INGEST:
            return self.role == role
        return _RANK[self.role] >= _RANK[role]


def hash_key(key: str) -> str:
    """SHA-256 of a key: keys are 256-bit random, so a slow password hash buys nothing."""
    return hashlib.sha256(key.encode()).hexdigest()


def new_key() -> str:
    """A fresh random key."""
    return KEY_PREFIX + secrets.token_urlsafe(32)


KEY_NAME_MAX = 200


def check_key_name(name: str) -> str:
    """A key's name as stored: trimmed, 1-200 characters, no control characters (a name is
    printed in `eqgw keys list`'s table and the audit log); ValueError saying why not."""
    name = name.strip()
    if not name:
        raise ValueError("a key's name must not be empty")
    if len(name) > KEY_NAME_MAX:
        raise ValueError(f"a key's name is at most {KEY_NAME_MAX} characters, not {len(name)}")
    if any(ord(c) < 32 or 127 <= ord(c) < 160 for c in name):
        raise ValueError("a key's name must not hold control characters (newlines, tabs, NUL)")
    return name


def create_key(engine: Engine, name: str, role: str) -> tuple[int, str]:
    """Store a new key with `role`; returns (id, key). The key is never stored or shown again."""
    name = check_key_name(name)
    if role not in ROLES:
        raise ValueError(f"unknown role {role!r}; use one of {', '.join(ROLES)}")
    key = new_key()
    with engine.begin() as conn:
        key_id = q.insert_key(
            conn,
            name=name,
            role=role,
            prefix=key[: len(KEY_PREFIX) + 6],
            key_hash=hash_key(key),
            now=time.time(),
        )
    return key_id, key


def ensure_first_admin(engine: Engine) -> str | None:
    """On a database that never had a key, create an admin key and return it (else None)."""
    with engine.connect() as conn:
        if q.count_keys(conn):
            return None
    _, key = create_key(engine, "first admin", "admin")
    return key


class KeyAuthenticator:
    """Looks keys up by hash, caching answers briefly so requests rarely touch the database."""

    def __init__(self, engine: Engine, cache_s: float = 5.0) -> None:
        self.engine = engine
        self.cache_s = cache_s
        self._cache: dict[str, tuple[float, Principal | None]] = {}
        self._used: dict[int, float] = {}

    def cached(self, key: str) -> tuple[bool, Principal | None]:
        """(hit, principal) from the cache alone (no I/O)."""
        h = hash_key(key)
        hit = self._cache.get(h)
        if hit is not None and hit[0] > time.monotonic():
            if hit[1] is not None:
                self._used[hit[1].key_id] = time.time()
            return True, hit[1]
        return False, None

    def lookup(self, key: str) -> Principal | None:
        """The active key's principal, or None (blocking: run it in a thread)."""
        h = hash_key(key)
        with self.engine.connect() as conn:
            row = q.key_by_hash(conn, h)
        principal = None
        if row is not None and row["revoked_at"] is None:
            principal = Principal(row["id"], row["name"], row["role"])
            self._used[principal.key_id] = time.time()
        if len(self._cache) > 10_000:
            self._cache.clear()  # unbounded guessing must not grow memory
        self._cache[h] = (time.monotonic() + self.cache_s, principal)
        return principal

    def forget(self) -> None:
        """Drop cached answers (after a revocation in this process)."""
        self._cache.clear()

    def flush_last_used(self) -> None:
        """Write last-used times (batched: a request never waits for it)."""
        used, self._used = self._used, {}
        if used:
            with self.engine.begin() as conn:
                q.touch_keys(conn, used)


def key_summary(row: dict[str, Any]) -> dict[str, Any]:
    """A key as the API lists it (never its hash)."""
    return {k: v for k, v in row.items() if k != "key_hash"}


__all__ = [
    "INGEST",
    "RANKED_ROLES",
    "ROLES",
    "KeyAuthenticator",
    "Principal",
    "create_key",
    "ensure_first_admin",
]
