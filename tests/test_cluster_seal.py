"""Gateways accept only NOTIFY payloads sealed with the cluster's secret: a database role with
no table privileges (which may NOTIFY on any channel) cannot make a gateway show values or
faults of units it does not read."""

from __future__ import annotations

import asyncio
import re
import uuid
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager

import psycopg
from sqlalchemy import text

from eqgw.cluster.fanout import FanOut, RemoteEvent, Sealer, encode_batches
from eqgw.cluster.leases import libpq_conninfo
from eqgw.ingest import events
from eqgw.ingest.events import Event, UnitRef
from eqgw.ingest.hub import EventHub
from eqgw.store.engine import create_engine
from eqgw.store.migrate import upgrade_engine
from tests.api_helpers import wait_for

CHANNEL = "eqgw_seal_test"


def test_seals_refuse_forgeries_stale_and_replayed_payloads() -> None:
    a, b = Sealer("s" * 64), Sealer("s" * 64)
    body = '{"o":"gw-a","e":[]}'
    sealed = a.seal(body, now=1000.0)
    assert b.open(sealed, now=1001.0) == body
    assert b.open(sealed, now=1001.0) is None  # the same payload again: a replay
    assert b.open(a.seal(body, now=1000.0), now=1000.0 + 31) is None  # stale
    assert b.open(Sealer("x" * 64).seal(body, now=1000.0), now=1000.0) is None  # other secret
    tampered = a.seal(body, now=1000.0).replace('"gw-a"', '"gw-b"')
    assert b.open(tampered, now=1000.0) is None
    assert b.open(body) is None  # unsealed (what gateways sent before)


@asynccontextmanager
async def _fanout(conninfo: str, instance: str, hub: EventHub) -> AsyncIterator[FanOut]:
    async def resync() -> None:
        return None

    fan = FanOut(
        conninfo, CHANNEL, instance, hub, EventHub(), on_remote=lambda _ev: True, on_resync=resync
    )
    await fan.start()
    try:
        yield fan
    finally:
        await fan.stop()


async def test_a_role_without_privileges_cannot_inject_events(pg_url: str) -> None:
    engine = create_engine(pg_url)
    upgrade_engine(engine)
    conninfo = libpq_conninfo(pg_url)
    rogue = f"eqgw_rogue_{uuid.uuid4().hex[:8]}"
    schema = re.search(r"search_path%3D(\w+)", pg_url)
    assert schema is not None
    with engine.begin() as conn:
        # It may use the schema (as any role may use `public`), and has no table privilege.
        conn.execute(text(f"CREATE ROLE {rogue} LOGIN"))
        conn.execute(text(f'GRANT USAGE ON SCHEMA "{schema[1]}" TO {rogue}'))
    try:
        hub_b = EventHub()
        seen = hub_b.subscribe(events.UNIT_KINDS)
        async with _fanout(conninfo, "gw-b", hub_b) as fan_b:
            # The rogue role reads nothing of the gateways' tables...
            async with await psycopg.AsyncConnection.connect(
                conninfo, user=rogue, autocommit=True
            ) as conn:
                try:
                    await conn.execute("SELECT secret FROM cluster_secrets")
                    raise AssertionError("the rogue role could read the secret")
                except psycopg.errors.InsufficientPrivilege:
                    pass
            # ...but may NOTIFY: an unsealed payload as gateways sent before, and one
            # sealed with a guessed secret, each claiming a 13.0 V unit and a fault.
            forged_ev = Event(events.LIVE, UnitRef("BUS-A", "BUS-A/can0", 30), 1.0, {"v24": 13.0})
            (plain,) = encode_batches("gw-a", [forged_ev])
            guessed = Sealer("0" * 64).seal(plain)
            async with await psycopg.AsyncConnection.connect(
                conninfo, user=rogue, autocommit=True
            ) as conn:
                for payload in (plain, guessed):
                    await conn.execute("SELECT pg_notify(%s, %s)", (CHANNEL, payload))

            forged: list[Event] = []

            async def settled() -> bool:
                ev = seen.get_nowait()
                if ev is not None:
                    forged.append(ev)
                return bool(forged) or fan_b.stats.rejected >= 2

            await wait_for(settled, what="both forged notifications refused")
            assert not forged, f"a forged event reached the hub: {forged}"

            # A real gateway's events still arrive.
            hub_a = EventHub()
            async with _fanout(conninfo, "gw-a", hub_a):
                real = Event(events.LIVE, UnitRef("BUS-A", "BUS-A/can0", 30), 2.0, {"v24": 27.5})

                async def arrived() -> RemoteEvent | None:
                    hub_a.publish(real)
                    await asyncio.sleep(0.2)
                    got = seen.get_nowait()
                    return got if isinstance(got, RemoteEvent) else None

                got = await wait_for(arrived, what="a genuine event from gw-a")
                assert got.data == {"v24": 27.5} and got.origin == "gw-a"
            assert fan_b.stats.rejected == 2
    finally:
        with engine.begin() as conn:
            conn.execute(text(f'REVOKE USAGE ON SCHEMA "{schema[1]}" FROM {rogue}'))
            conn.execute(text(f"DROP ROLE {rogue}"))
        engine.dispose()
