"""The audit log: its rows, anonymous refusals counted instead of stored one by one, retention.

A request without a valid key costs its sender nothing, so each one written as its own audit
row would let anyone grow the table without bound. They are counted in memory per (action,
status) and written as one row per flush (every few seconds): the row's `request` holds the
count and the first and last time, so the log still says that it happened, how much and when.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Awaitable, Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, NotRequired, TypedDict, Unpack

from sqlalchemy import Engine

from eqgw.security import repository as q

if TYPE_CHECKING:
    from eqgw.security.keys import Person, Principal


class AuditFields(TypedDict):
    """What an audit entry says besides who and the action, as `Runtime.audit`,
    `AuditLog.append` and `audit_entry` take it (keywords; the ones left out are None)."""

    outcome: str
    status: int
    detail: NotRequired[str | None]
    vehicle_id: NotRequired[str | None]
    target: NotRequired[str | None]
    request: NotRequired[dict[str, Any] | None]
    command_id: NotRequired[str | None]
    person: NotRequired[Person | None]


# Distinct (action, status) pairs kept between flushes; beyond it they are merged into one.
MAX_KINDS = 256
OTHER = "(other actions)"


@dataclass(slots=True)
class _Count:
    count: int
    first_ts: float
    last_ts: float
    detail: str | None
    vehicle_ids: set[str]


class AnonymousRefusals:
    """Refusals of requests without a valid key, counted until the next flush."""

    def __init__(self) -> None:
        self._counts: dict[tuple[str, int], _Count] = {}

    def add(self, action: str, status: int, detail: str | None, vehicle_id: str | None) -> None:
        """Count one refusal (no I/O)."""
        now = time.time()
        key = (action, status)
        if key not in self._counts and len(self._counts) >= MAX_KINDS:
            key = (OTHER, status)
        c = self._counts.get(key)
        if c is None:
            c = self._counts[key] = _Count(0, now, now, detail, set())
        c.count += 1
        c.last_ts = now
        if vehicle_id is not None and len(c.vehicle_ids) < 10:
            c.vehicle_ids.add(vehicle_id[:64])

    def take(self) -> list[dict[str, Any]]:
        """The audit rows of what was counted since the last call (and forget it)."""
        counts, self._counts = self._counts, {}
        rows = []
        for (action, status), c in counts.items():
            vehicle = next(iter(c.vehicle_ids)) if len(c.vehicle_ids) == 1 else None
            rows.append(
                {
                    "ts": c.last_ts,
                    "key_id": None,
                    "key_name": None,
                    "role": None,
                    "action": action,
                    "vehicle_id": vehicle,
                    "target": None,
                    "request": {
                        "count": c.count,
                        "first_ts": c.first_ts,
                        "last_ts": c.last_ts,
                        "vehicle_ids": sorted(c.vehicle_ids),
                    },
                    "outcome": "refused",
                    "status_code": status,
                    "detail": f"{c.count} request(s) without a valid key: {c.detail}"[:2000],
                    "command_id": None,
                }
            )
        return rows

    def flush(self, engine: Engine) -> int:
        """Write what was counted (blocking: run it in a thread); returns the rows written.
        On failure the counts are put back for the next flush."""
        rows = self.take()
        if not rows:
            return 0
        try:
            with engine.begin() as conn:
                for row in rows:
                    q.add_audit(conn, row)
        except Exception:
            for row in rows:
                r = row["request"]
                key = (row["action"], row["status_code"])
                c = self._counts.setdefault(
                    key, _Count(0, r["first_ts"], r["last_ts"], None, set(r["vehicle_ids"]))
                )
                c.count += r["count"]
                c.first_ts = min(c.first_ts, r["first_ts"])
                c.detail = c.detail or row["detail"]
            raise
        return len(rows)


def audit_entry(
    who: Principal | None,
    action: str,
    *,
    key_name: str | None = None,
    **fields: Unpack[AuditFields],
) -> dict[str, Any]:
    """An audit log row as `Runtime.audit` writes it, for an entry written in the same
    transaction as the change it records (`key_name`: who, without a key: a command line;
    the person of a single sign-on session is the key's own unless given)."""
    person = fields.get("person")
    if person is None and who is not None:
        person = who.person
    request = fields.get("request")
    return {
        "ts": time.time(),
        "key_id": who.key_id if who else None,
        "key_name": _clip(who.name if who else key_name, 200),
        "role": who.role if who else None,
        "action": _clip(action, 64),
        "vehicle_id": _clip(fields.get("vehicle_id"), 64),
        "target": _clip(fields.get("target"), 200),
        "request": _json_safe(request) if request is not None else None,
        "outcome": fields["outcome"],
        "status_code": fields["status"],
        "detail": _clip(fields.get("detail"), 2000),
        "command_id": _clip(fields.get("command_id"), 36),
        "subject": _clip(person.subject, 255) if person else None,
        "email": _clip(person.email, 320) if person else None,
    }


def _clip(text: str | None, limit: int) -> str | None:
    """`text` fit for a text column of `limit` characters (NUL replaced, the end cut)."""
    if not text:
        return text
    text = _storable(text)
    return text if len(text) <= limit else text[: limit - 1] + "\u2026"


def _storable(text: str) -> str:
    """`text` with NUL characters and lone surrogates replaced by U+FFFD."""
    text = text.replace("\x00", "\ufffd")
    try:
        text.encode("utf-8")
    except UnicodeEncodeError:
        text = text.encode("utf-8", "surrogatepass").decode("utf-8", "replace")
    return text


def _json_safe(value: Any) -> Any:
    """`value` as JSON and PostgreSQL can store it (see `AuditLog.append`)."""
    if isinstance(value, float) and not math.isfinite(value):
        return repr(value)
    if isinstance(value, str):
        return _storable(value)
    if isinstance(value, dict):
        return {_json_safe(str(k)): _json_safe(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_json_safe(v) for v in value]
    return value


@dataclass
class AuditLog:
    """The audit log as routes append to it (`Runtime.audit`), with the anonymous refusals it
    counts until the next flush (`key_upkeep`)."""

    refusals: AnonymousRefusals = field(default_factory=AnonymousRefusals)

    async def append(
        self,
        db: Callable[..., Awaitable[Any]],
        who: Principal | None,
        action: str,
        **fields: Unpack[AuditFields],
    ) -> None:
        """Append to the audit log. What the client sent is stored as it can be: text
        clipped to its column, NUL characters (which PostgreSQL text cannot hold) as U+FFFD,
        non-finite numbers (which JSON cannot hold) as strings, so that a refusal of odd
        input is recorded instead of failing. A refusal without a valid key is counted and
        written with the others of its action at the next flush (`AnonymousRefusals`), unless
        it names a `person` (one the OpenID provider vouched for, refused a session). The
        person of a single sign-on session is named (subject, email) with its key."""
        if who is None and fields["outcome"] == "refused" and fields.get("person") is None:
            self.refusals.add(
                _clip(action, 64) or "",
                fields["status"],
                fields.get("detail"),
                fields.get("vehicle_id"),
            )
            return
        # (audit_entry names the person of a key's session)
        await db(q.add_audit, audit_entry(who, action, **fields))


def prune_audit(
    engine: Engine,
    retention_days: float,
    batch: int = 5000,
    stop: threading.Event | None = None,
) -> int:
    """Delete audit entries older than `retention_days` (0: keep them all), a batch a
    transaction; returns how many. With `stop` set, it ends before its next transaction
    (what it deleted stays deleted; the next prune goes on)."""
    if retention_days <= 0:
        return 0
    before = time.time() - retention_days * 86400.0
    total = 0
    while True:
        if stop is not None and stop.is_set():
            return total
        with engine.begin() as conn:
            n = q.prune_audit(conn, before, batch)
        total += n
        if n < batch:
            return total
