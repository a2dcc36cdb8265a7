"""Bus leases as PostgreSQL session advisory locks, held on one connection per gateway.

A lock lives exactly as long as the session that took it: a gateway whose process dies loses
its connection and the server frees its locks at once. A gateway the server stops hearing
from (a lost host, a blackholed path, a hung process) loses its session, and so its locks,
after `idle_session_timeout` (the lease's time to live, on the server's clock; the lease
rounds keep it busy) or the session's TCP keepalive, whichever comes first. No table, no
clock shared between hosts: each side measures the lease on its own clock (the gateway fences
itself before it can have expired). Who holds what is visible to anyone in `pg_locks` joined
with `pg_stat_activity.application_name`, which carries `eqgw:<namespace>:<instance id>`.
"""

from __future__ import annotations

import hashlib
import logging
from dataclasses import dataclass

import psycopg
from sqlalchemy import Engine
from sqlalchemy.engine import URL

from eqgw.store.engine import sync_url

log = logging.getLogger(__name__)

APP_PREFIX = "eqgw"
NAMEDATALEN = 63  # longer application names are cut by the server


def libpq_conninfo(database_url: str | URL) -> str:
    """The database URL as a libpq URI (keeps `options=-csearch_path=...`)."""
    url = sync_url(database_url).set(drivername="postgresql")
    return url.render_as_string(hide_password=False)


def namespace_of(database: str, schema: str) -> str:
    """A short tag of the database and schema: gateways of one deployment share it, tests in
    other schemas of the same server (and their locks and channels) never meet."""
    return hashlib.blake2b(f"{database}\0{schema}".encode(), digest_size=4).hexdigest()


def lease_key(namespace: str, bus: str) -> int:
    """The advisory lock key of a bus: a stable signed 64-bit hash of namespace and name."""
    digest = hashlib.blake2b(f"eqgw-bus\0{namespace}\0{bus}".encode(), digest_size=8).digest()
    return int.from_bytes(digest, "big", signed=True)


def _key_of_lock(classid: int, objid: int) -> int:
    """pg_locks shows a bigint advisory key as its high (classid) and low (objid) halves."""
    unsigned = (classid << 32) | objid
    return unsigned - (1 << 64) if unsigned >= 1 << 63 else unsigned


@dataclass(slots=True)
class Holders:
    """Who holds which bus lease, and which gateways are up (seen by one query)."""

    owners: dict[str, str]  # bus -> instance id
    instances: list[str]  # instance ids with a lease connection, sorted


class LeaseConnection:
    """The one connection whose session holds this gateway's bus locks."""

    def __init__(
        self,
        database_url: str | URL,
        instance_id: str,
        *,
        keepalive: tuple[int, int, int] = (3, 2, 3),
        connect_timeout: float = 5.0,
        ttl_s: float | None = None,
        statement_timeout_s: float | None = None,
    ) -> None:
        self.conninfo = libpq_conninfo(database_url)
        self.instance_id = instance_id
        self.keepalive = keepalive
        self.connect_timeout = connect_timeout
        self.ttl_s = ttl_s
        self.statement_timeout_s = statement_timeout_s
        self.namespace = ""
        self._conn: psycopg.AsyncConnection[tuple[object, ...]] | None = None
        self._keys: dict[str, int] = {}

    @property
    def connected(self) -> bool:
        return self._conn is not None and not self._conn.closed

    @property
    def application_name(self) -> str:
        return f"{APP_PREFIX}:{self.namespace}:{self.instance_id}"[:NAMEDATALEN]

    async def connect(self) -> None:
        """Open the session, learn the namespace, name the session after this gateway."""
        conn = await psycopg.AsyncConnection.connect(
            self.conninfo,
            autocommit=True,
            connect_timeout=max(1, round(self.connect_timeout)),
            application_name=f"{APP_PREFIX}-starting",
        )
        try:
            idle, interval, count = self.keepalive
            cur = await conn.execute("SELECT current_database(), current_schema()")
            row = await cur.fetchone()
            assert row is not None
            self.namespace = namespace_of(str(row[0]), str(row[1]))
            # The server notices a vanished host by these, then frees its locks.
            await conn.execute(f"SET tcp_keepalives_idle = {int(idle)}")
            await conn.execute(f"SET tcp_keepalives_interval = {int(interval)}")
            await conn.execute(f"SET tcp_keepalives_count = {int(count)}")
            if self.statement_timeout_s is not None:
                ms = max(1, int(self.statement_timeout_s * 1000))
                await conn.execute(f"SET statement_timeout = {ms}")
            if self.ttl_s is not None:
                # The lease's time to live on the server: a session silent this long (its
                # gateway cut off, whatever the network does to the socket) is ended, and
                # every lock it holds freed. PostgreSQL 14 and later.
                if conn.info.server_version >= 140000:
                    ms = max(1, int(self.ttl_s * 1000))
                    await conn.execute(f"SET idle_session_timeout = {ms}")
                else:
                    log.warning(
                        "PostgreSQL %s has no idle_session_timeout: a gateway cut off from the "
                        "database loses its buses only by TCP keepalive",
                        conn.info.server_version,
                    )
            await conn.execute(
                "SELECT set_config('application_name', %s, false)", (self.application_name,)
            )
        except BaseException:
            await conn.close()
            raise
        self._conn = conn

    async def close(self) -> None:
        """End the session: every lock it holds is freed."""
        conn, self._conn = self._conn, None
        if conn is not None:
            await conn.close()

    def key(self, bus: str) -> int:
        key = self._keys.get(bus)
        if key is None:
            key = self._keys[bus] = lease_key(self.namespace, bus)
        return key

    def _require(self) -> psycopg.AsyncConnection[tuple[object, ...]]:
        if self._conn is None or self._conn.closed:
            raise psycopg.OperationalError("lease connection is not open")
        return self._conn

    async def try_acquire(self, bus: str) -> bool:
        """Take the bus's lock if nobody holds it (never waits)."""
        cur = await self._require().execute("SELECT pg_try_advisory_lock(%s)", (self.key(bus),))
        row = await cur.fetchone()
        return bool(row and row[0])

    async def release(self, bus: str) -> None:
        await self._require().execute("SELECT pg_advisory_unlock(%s)", (self.key(bus),))

    async def holders(self, buses: list[str]) -> Holders:
        """Owners of `buses` and the gateways of this namespace that are up; one round trip,
        which also proves the session (and so every lock it holds) is still alive."""
        prefix = f"{APP_PREFIX}:{self.namespace}:"
        cur = await self._require().execute(
            """
            SELECT a.application_name, l.classid::bigint, l.objid::bigint
            FROM pg_stat_activity a
            LEFT JOIN pg_locks l
              ON l.pid = a.pid AND l.locktype = 'advisory' AND l.granted AND l.objsubid = 1
            WHERE a.datname = current_database() AND starts_with(a.application_name, %s)
            """,
            (prefix,),
        )
        by_key = {self.key(b): b for b in buses}
        owners: dict[str, str] = {}
        instances: set[str] = set()
        for name, classid, objid in await cur.fetchall():
            instance = str(name)[len(prefix) :]
            instances.add(instance)
            if classid is None or objid is None:
                continue
            assert isinstance(classid, int) and isinstance(objid, int)
            bus = by_key.get(_key_of_lock(classid, objid))
            if bus is not None:
                owners[bus] = instance
        return Holders(owners, sorted(instances))


class StartupLock:
    """Gateways starting together on one PostgreSQL start one at a time: migrations, the first
    admin key and any seeding done at start would otherwise race (a session advisory lock,
    held on its own connection from before the migrations until the gateway serves)."""

    def __init__(self, engine: Engine, wait_s: float = 120.0) -> None:
        self.engine = engine
        self.wait_s = wait_s
        self._conn: psycopg.Connection[tuple[object, ...]] | None = None

    def acquire(self) -> None:
        from eqgw.store.engine import is_sqlite

        if is_sqlite(self.engine.url) or self._conn is not None:
            return
        conn = psycopg.connect(
            libpq_conninfo(self.engine.url), autocommit=True, application_name="eqgw-starting"
        )
        try:
            row = conn.execute("SELECT current_database(), current_schema()").fetchone()
            assert row is not None
            key = lease_key(namespace_of(str(row[0]), str(row[1])), "\0startup")
            # A gateway stuck in its start must not keep the others out for ever.
            conn.execute(f"SET lock_timeout = '{int(self.wait_s * 1000)}ms'")
            try:
                conn.execute("SELECT pg_advisory_lock(%s)", (key,))
            except psycopg.errors.LockNotAvailable:
                log.warning("another gateway is still starting after %.0f s; going on", self.wait_s)
                conn.close()
                return
        except BaseException:
            conn.close()
            raise
        self._conn = conn

    def release(self) -> None:
        """Let the next gateway start (closing the session frees the lock); idempotent."""
        conn, self._conn = self._conn, None
        if conn is not None:
            conn.close()
