"""API keys and roles: generation, hashing, cached lookup, and the FastAPI dependencies."""

from __future__ import annotations

import hashlib
import secrets
import time
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field, replace
from types import MappingProxyType
from typing import Any, TypeVar

from sqlalchemy import Engine

from eqgw.security import repository as q

# Ranked roles: each includes the ones before it.
RANKED_ROLES = ("viewer", "operator", "admin")
# `ingest` (edge forwarders posting frames) stands apart: it satisfies only itself, and no
# other role satisfies it, so a vehicle's key can never read the fleet and a reader's key
# can never write history.
INGEST = "ingest"
ROLES = (*RANKED_ROLES, INGEST)
_RANK = {role: i for i, role in enumerate(RANKED_ROLES)}
KEY_PREFIX = "eqgw_"
# The listed prefix of a person's key row (single sign-on, eqgw.security.oidc): its secret is
# never made, and it works only through that person's sessions.
SSO_KEY_PREFIX = "sso"


_T = TypeVar("_T")
_NO_DEPOTS: Mapping[str, str | None] = MappingProxyType({})


@dataclass(frozen=True, slots=True)
class Scope:
    """The vehicles a key may see and command: every vehicle (both sets None), or those of
    some depots (`groups`, as the fleet file's `depot`) and/or some vehicles by id."""

    groups: frozenset[str] | None = None
    vehicles: frozenset[str] | None = None
    # Each configured vehicle's depot: a group is resolved through it.
    depots: Mapping[str, str | None] = field(
        default_factory=lambda: _NO_DEPOTS, compare=False, hash=False
    )

    @classmethod
    def of(
        cls,
        groups: Iterable[str] | None,
        vehicles: Iterable[str] | None,
        depots: Mapping[str, str | None] = _NO_DEPOTS,
    ) -> Scope:
        """A scope from stored lists (None for both: every vehicle)."""
        g = frozenset(groups) if groups is not None else None
        v = frozenset(vehicles) if vehicles is not None else None
        if g is not None and v is None:
            v = frozenset()
        if v is not None and g is None:
            g = frozenset()
        return cls(g, v, depots)

    @property
    def everything(self) -> bool:
        """Whether this is the whole fleet."""
        return self.groups is None and self.vehicles is None

    def allows(self, vehicle_id: str | None) -> bool:
        """Whether the vehicle is in scope (a fleet-wide object, None, only for everything)."""
        if self.everything:
            return True
        if vehicle_id is None:
            return False
        if vehicle_id in (self.vehicles or ()):
            return True
        depot = self.depots.get(vehicle_id)
        return depot is not None and depot in (self.groups or ())

    def vehicle_ids(self) -> frozenset[str] | None:
        """The vehicle ids in scope, for a query's filter (None: no filter)."""
        if self.everything:
            return None
        groups = self.groups or frozenset()
        in_groups = {vid for vid, depot in self.depots.items() if depot in groups}
        return (self.vehicles or frozenset()) | in_groups

    def within(self, other: Scope) -> bool:
        """Whether this scope is no wider than `other` (each group and vehicle of it held)."""
        if other.everything:
            return True
        if self.everything:
            return False
        return (self.groups or frozenset()) <= (other.groups or frozenset()) and all(
            other.allows(v) for v in self.vehicles or ()
        )

    def as_json(self) -> dict[str, list[str]] | None:
        """As listed by the API: None for every vehicle."""
        if self.everything:
            return None
        return {"groups": sorted(self.groups or ()), "vehicles": sorted(self.vehicles or ())}

    @classmethod
    def union(cls, scopes: Iterable[Scope], depots: Mapping[str, str | None] = _NO_DEPOTS) -> Scope:
        """Every vehicle any of `scopes` holds (none at all for no scope)."""
        groups: set[str] = set()
        vehicles: set[str] = set()
        for scope in scopes:
            if scope.everything:
                return cls(None, None, depots)
            groups |= scope.groups or set()
            vehicles |= scope.vehicles or set()
        return cls(frozenset(groups), frozenset(vehicles), depots)


EVERYTHING = Scope()


@dataclass(frozen=True, slots=True)
class Grant:
    """A role over a scope: what one group of a person's single sign-on gives them."""

    role: str
    scope: Scope

    def as_json(self) -> dict[str, Any]:
        """As stored with a session and listed by the API."""
        return {"role": self.role, "scope": self.scope.as_json()}


@dataclass(frozen=True, slots=True)
class Person:
    """Who signed in through single sign-on: the provider's subject, and their email."""

    subject: str
    email: str | None = None


@dataclass(frozen=True, slots=True)
class Principal:
    """The key a request was made with."""

    key_id: int
    name: str
    role: str
    scope: Scope = EVERYTHING
    # The first key of this key's rotations (its own id when never rotated).
    lineage: int = 0
    # When the key stops working (expiry, or the end of a rotation's overlap); None: never.
    ends_at: float | None = None
    # A single sign-on session's person, and the roles their groups gave them, each over its
    # own scope (then `role` is the strongest and `scope` all of them); empty for a key.
    person: Person | None = None
    grants: tuple[Grant, ...] = ()

    def sees(self, vehicle_id: str | None) -> bool:
        """Whether the key's scope holds this vehicle."""
        return self.scope.allows(vehicle_id)

    def allows(self, role: str) -> bool:
        """Whether this key's role includes `role` (admin > operator > viewer; ingest alone)."""
        if role == INGEST or self.role == INGEST:
            return self.role == role
        return _RANK[self.role] >= _RANK[role]

    def role_for(self, vehicle_id: str) -> str | None:
        """The strongest role this principal holds over a vehicle (None: out of scope)."""
        if not self.grants:
            return self.role if self.sees(vehicle_id) else None
        held = [g.role for g in self.grants if g.scope.allows(vehicle_id)]
        return strongest(held) if held else None

    def acting_as(self, role: str) -> Principal:
        """This principal for something that needs `role`: a key as it is; a person with
        grants narrowed to the vehicles where some grant holds `role` or a stronger one (an
        operator of North and viewer of South acts as an operator on North only)."""
        if not self.grants or role == INGEST:
            return self
        held = [g.scope for g in self.grants if _RANK[g.role] >= _RANK[role]]
        return replace(self, scope=Scope.union(held, self.scope.depots))


def strongest(roles: Iterable[str]) -> str:
    """The strongest of ranked roles (viewer for none)."""
    return max(roles, key=_RANK.__getitem__, default=RANKED_ROLES[0])


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


def create_key(
    engine: Engine,
    name: str,
    role: str,
    *,
    scope: Scope = EVERYTHING,
    expires_at: float | None = None,
) -> tuple[int, str]:
    """Store a new key with `role`, `scope` and an optional expiry; returns (id, key). The key
    is never stored or shown again."""
    name = check_key_name(name)
    if role not in ROLES:
        raise ValueError(f"unknown role {role!r}; use one of {', '.join(ROLES)}")
    key = new_key()
    with engine.begin() as conn:
        key_id = q.insert_key(conn, **_key_values(key, name, role, scope, expires_at))
    return key_id, key


def _key_values(
    key: str, name: str, role: str, scope: Scope, expires_at: float | None
) -> dict[str, Any]:
    listed = scope.as_json()
    return {
        "name": name,
        "role": role,
        "prefix": key[: len(KEY_PREFIX) + 6],
        "key_hash": hash_key(key),
        "now": time.time(),
        "scope_groups": None if listed is None else listed["groups"],
        "scope_vehicles": None if listed is None else listed["vehicles"],
        "expires_at": expires_at,
    }


class KeyNotFound(LookupError):
    """No active key with that id (or none the caller may manage)."""


def rotate_key(
    engine: Engine,
    key_id: int,
    *,
    overlap_s: float,
    expires_at: float | None = None,
    within: Scope = EVERYTHING,
    scope: Scope | None = None,
) -> tuple[int, str, float]:
    """Replace an active key: a new key with its name, role and scope (or `scope`, which
    must lie within the old one's: a key can be narrowed, never widened, by rotation) and
    `expires_at`, the old one revoked `overlap_s` seconds from now. Returns (new id, new key,
    when the old one stops). KeyNotFound when there is no active key `key_id` whose scope is
    `within`; ValueError for a wider `scope`."""
    now = time.time()
    key = new_key()
    # Read then write: SQLite's write lock taken up front (a deferred one fails at once when
    # another writer holds it, instead of waiting).
    with engine.execution_options(sqlite_begin="IMMEDIATE").begin() as conn:
        old = q.get_key(conn, key_id)
        if old is None or not key_active(old, now) or not scope_of(old).within(within):
            raise KeyNotFound(key_id)
        if is_person_key(old):
            raise ValueError(
                "this is a person's single sign-on: it has no key to rotate (revoking it ends "
                "their sessions)"
            )
        ends = now + overlap_s
        if old["expires_at"] is not None:
            ends = min(ends, old["expires_at"])
        old_scope = scope_of(old, within.depots)
        if scope is not None and not scope.within(old_scope):
            raise ValueError("a rotated key's scope must lie within the old key's")
        values = _key_values(key, old["name"], old["role"], scope or old_scope, expires_at)
        new_id = q.insert_key(conn, **values, lineage=old["lineage"] or old["id"])
        q.revoke_key(conn, key_id, ends)
    return new_id, key, ends


def is_person_key(row: Mapping[str, Any]) -> bool:
    """Whether a key row stands for a person of single sign-on (no key: their sessions only)."""
    return bool(row["prefix"] == SSO_KEY_PREFIX)


def key_active(row: Mapping[str, Any], now: float) -> bool:
    """Whether a stored key still works at `now` (not revoked, not expired)."""
    revoked, expires = row["revoked_at"], row["expires_at"]
    return (revoked is None or revoked > now) and (expires is None or expires > now)


def scope_of(row: Mapping[str, Any], depots: Mapping[str, str | None] = _NO_DEPOTS) -> Scope:
    """A stored key's scope."""
    return Scope.of(row["scope_groups"], row["scope_vehicles"], depots)


def ensure_first_admin(engine: Engine) -> str | None:
    """On a database that never had a key, create an admin key and return it (else None)."""
    with engine.connect() as conn:
        if q.count_keys(conn):
            return None
    _, key = create_key(engine, "first admin", "admin")
    return key


@dataclass(frozen=True, slots=True)
class SessionAuth:
    """A browser session: the principal of its key, and the token its writes must carry."""

    principal: Principal
    csrf_token: str
    token_hash: str


def _active(
    row: Mapping[str, Any] | None, now: float, depots: Mapping[str, str | None] = _NO_DEPOTS
) -> Principal | None:
    """The principal of a key row (its role, scope and end), or None when the key may not be
    used at `now` (revoked or expired, or a person's, which only their sessions use). Keys,
    login codes and browser sessions all resolve through it."""
    if row is None or not key_active(row, now) or is_person_key(row):
        return None
    return _principal(row, depots)


def _principal(row: Mapping[str, Any], depots: Mapping[str, str | None]) -> Principal:
    ends = [t for t in (row["revoked_at"], row["expires_at"]) if t is not None]
    return Principal(
        row["id"],
        row["name"],
        row["role"],
        scope=scope_of(row, depots),
        lineage=row["lineage"] or row["id"],
        ends_at=min(ends) if ends else None,
    )


def _person_session(
    row: Mapping[str, Any], now: float, depots: Mapping[str, str | None]
) -> Principal | None:
    """The principal of a single sign-on session's row: the person's key row (its id, name
    and revocation) with the grants stored at sign-in; None when the key is revoked."""
    if not key_active(row, now) or not is_person_key(row):
        return None
    grants = tuple(
        Grant(
            g["role"],
            Scope(None, None, depots)
            if g["scope"] is None
            else Scope.of(g["scope"]["groups"], g["scope"]["vehicles"], depots),
        )
        for g in row["grants"]
    )
    return replace(
        _principal(row, depots),
        role=strongest(g.role for g in grants),
        scope=Scope.union((g.scope for g in grants), depots),
        person=Person(row["person_subject"], row["person_email"]),
        grants=grants,
    )


class KeyAuthenticator:
    """Looks keys up by hash, caching answers briefly so requests rarely touch the database."""

    def __init__(
        self,
        engine: Engine,
        cache_s: float = 5.0,
        depots: Mapping[str, str | None] = _NO_DEPOTS,
    ) -> None:
        self.engine = engine
        self.cache_s = cache_s
        self.depots = depots  # each configured vehicle's depot, for scopes by group
        # Answers by hash: a key's principal, a session cookie's session (None: refused).
        self._cache: dict[str, tuple[float, Principal | None]] = {}
        self._sessions: dict[str, tuple[float, SessionAuth | None]] = {}
        self._used: dict[int, float] = {}

    def _usable(self, principal: Principal | None, now: float) -> Principal | None:
        """The principal if its key still works at `now` (a cached answer may outlive an
        expiry or a rotation's overlap), its use noted for the last-used flush."""
        if principal is None or (principal.ends_at is not None and principal.ends_at <= now):
            return None
        self._used[principal.key_id] = now
        return principal

    def _remember(self, cache: dict[str, tuple[float, _T]], h: str, answer: _T) -> _T:
        if len(cache) > 10_000:
            cache.clear()  # unbounded guessing must not grow memory
        cache[h] = (time.monotonic() + self.cache_s, answer)
        return answer

    def cached(self, key: str) -> tuple[bool, Principal | None]:
        """(hit, principal) from the cache alone (no I/O)."""
        hit = self._cache.get(hash_key(key))
        if hit is None or hit[0] <= time.monotonic():
            return False, None
        return True, self._usable(hit[1], time.time())

    def last_known(self, key: str) -> tuple[bool, Principal | None]:
        """(known, principal): the last answer the database gave for `key`, however old (for
        while the database does not answer; a key revoked meanwhile elsewhere still works
        here until it answers again)."""
        hit = self._cache.get(hash_key(key))
        if hit is None:
            return False, None
        return True, self._usable(hit[1], time.time())

    def last_known_session(self, token: str) -> tuple[bool, SessionAuth | None]:
        """`last_known` for a session cookie."""
        hit = self._sessions.get(hash_key(token))
        if hit is None:
            return False, None
        session = hit[1]
        if session is None or self._usable(session.principal, time.time()) is None:
            return True, None
        return True, session

    def lookup(self, key: str) -> Principal | None:
        """The active key's principal, or None (blocking: run it in a thread)."""
        h = hash_key(key)
        with self.engine.connect() as conn:
            row = q.key_by_hash(conn, h)
        now = time.time()
        principal = self._usable(_active(row, now, self.depots), now)
        return self._remember(self._cache, h, principal)

    def cached_session(self, token: str) -> tuple[bool, SessionAuth | None]:
        """(hit, session) from the cache alone (no I/O)."""
        hit = self._sessions.get(hash_key(token))
        if hit is None or hit[0] <= time.monotonic():
            return False, None
        session = hit[1]
        if session is None or self._usable(session.principal, time.time()) is None:
            return True, None
        return True, session

    def lookup_session(self, token: str) -> SessionAuth | None:
        """The session of a cookie with its key resolved like a key, or None (blocking)."""
        from eqgw.security import session_repository as sq

        h = hash_key(token)
        now = time.time()
        with self.engine.connect() as conn:
            row = sq.session_key(conn, h, now)
        if row is not None and row["grants"] is not None:
            principal = self._usable(_person_session(row, now, self.depots), now)
        else:
            principal = self._usable(_active(row, now, self.depots), now)
        session = None
        if row is not None and principal is not None:
            session = SessionAuth(principal, row["csrf_token"], h)
        return self._remember(self._sessions, h, session)

    def forget(self) -> None:
        """Drop cached answers (after a revocation or a logout in this process)."""
        self._cache.clear()
        self._sessions.clear()

    def flush_last_used(self) -> None:
        """Write last-used times (batched: a request never waits for it, and a key in steady
        use costs one UPDATE per flush, every 10 s, not one per request)."""
        used, self._used = self._used, {}
        if used:
            with self.engine.begin() as conn:
                q.touch_keys(conn, used)


def key_summary(row: Mapping[str, Any], now: float | None = None) -> dict[str, Any]:
    """A key as the API lists it (never its hash): its scope as one object, whether active."""
    out = {
        k: v
        for k, v in row.items()
        if k not in ("key_hash", "scope_groups", "scope_vehicles", "lineage")
    }
    out["scope"] = scope_of(row).as_json()
    out["lineage"] = row["lineage"] or row["id"]
    out["active"] = key_active(row, time.time() if now is None else now)
    return out


__all__ = [
    "EVERYTHING",
    "INGEST",
    "RANKED_ROLES",
    "ROLES",
    "SSO_KEY_PREFIX",
    "Grant",
    "KeyAuthenticator",
    "Person",
    "Principal",
    "Scope",
    "SessionAuth",
    "create_key",
    "ensure_first_admin",
    "rotate_key",
]
