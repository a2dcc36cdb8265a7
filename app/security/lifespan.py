"""Security's parts of a running gateway's lifespan (see app/main.py): the first admin key,
and the upkeep of keys' last use, anonymous refusals, the audit and the write limit's log."""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import AsyncIterator, Callable
from contextlib import asynccontextmanager
from typing import TYPE_CHECKING

from eqgw.security.audit import prune_audit
from eqgw.security.keys import ensure_first_admin
from eqgw.security.limit_repository import prune_write_hits
from eqgw.tasks import heals, in_thread_until_stopped

if TYPE_CHECKING:
    from sqlalchemy import Engine

    from eqgw.supervisor import Supervisor
    from eqgw.web.runtime import Runtime
    from eqgw.web.settings import ApiSettings

log = logging.getLogger(__name__)
KEY_FLUSH_S = 10.0
AUDIT_PRUNE_S = 3600.0
# Refusals without a key are written at most this often (one row per action each time).
REFUSALS_FLUSH_S = 60.0


async def first_admin(
    engine: Engine,
    api: ApiSettings,
    on_first_key: Callable[[str], None] | None,
    on_login_code: Callable[[str], None] | None,
) -> None:
    """On a database that never had a key: the admin key created and handed to
    `on_first_key` (once), then a one-time login code of it to `on_login_code`."""
    first_key = await asyncio.to_thread(ensure_first_admin, engine)
    if first_key is None:
        return
    if on_first_key is not None:
        on_first_key(first_key)
    if on_login_code is not None:
        ttl = api.login_code_ttl_s
        on_login_code(await asyncio.to_thread(_login_code_of, engine, first_key, ttl))


def _login_code_of(engine: Engine, key: str, ttl_s: float) -> str:
    """A one-time login code of `key` (the first admin's, for the first start's link)."""
    from eqgw.security import repository as q
    from eqgw.security.keys import hash_key
    from eqgw.security.login_codes import create_login_code

    with engine.connect() as conn:
        row = q.key_by_hash(conn, hash_key(key))
    assert row is not None
    # Its own transaction that writes first (SQLite: a read that then writes cannot wait for
    # the write lock; a first write waits its busy timeout).
    with engine.begin() as conn:
        return create_login_code(conn, int(row["id"]), ttl_s)


@asynccontextmanager
async def key_upkeep(rt: Runtime, tasks: Supervisor) -> AsyncIterator[None]:
    """The loop that records keys' use (supervised); at the end their last use and the
    counted refusals written once more."""
    try:
        async with tasks.running("api key last-used and audit", lambda: flush_keys(rt)):
            yield
    finally:
        rt.keys.flush_last_used()
        _flush_refusals(rt)


async def flush_keys(rt: Runtime) -> None:
    """Every KEY_FLUSH_S, keys' last use; every REFUSALS_FLUSH_S, the anonymous refusals
    counted; every AUDIT_PRUNE_S, the audit retention and the write limit's expired log."""
    pruned_at = refusals_at = time.monotonic()
    pruned_at -= AUDIT_PRUNE_S  # the first prune soon after start
    while True:
        await asyncio.sleep(KEY_FLUSH_S)
        try:
            await asyncio.to_thread(rt.keys.flush_last_used)
            if time.monotonic() - refusals_at >= REFUSALS_FLUSH_S:
                refusals_at = time.monotonic()
                await asyncio.to_thread(rt.audit_log.refusals.flush, rt.engine)
            if time.monotonic() - pruned_at >= AUDIT_PRUNE_S:
                pruned_at = time.monotonic()
                # Cancelled (the gateway stops), it ends before its next transaction.
                n = await in_thread_until_stopped(
                    lambda stop: prune_audit(rt.engine, rt.api.audit_retention_days, stop=stop)
                )
                if n:
                    log.info("audit retention: deleted %d entries", n)
                await rt.db(prune_write_hits, rt.api.write_window_s)
        except Exception as exc:  # the database may be away; this waits for next round
            if not heals(exc):
                raise  # its supervisor stops it (a fatal one: the process)
            log.warning("recording key use or audit failed: %s", exc)


def _flush_refusals(rt: Runtime) -> None:
    try:
        rt.audit_log.refusals.flush(rt.engine)
    except Exception as exc:
        log.warning("anonymous refusals not written at shutdown: %s", exc)
