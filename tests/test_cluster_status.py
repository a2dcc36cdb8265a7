"""A gateway's own view of who reads which bus (/readyz `cluster`) is consistent at every
moment: a bus it has taken is among its owned buses and has it as owner at once, also while
the bus's reader is still being started."""

from __future__ import annotations

import asyncio
from typing import Any

from eqgw.bus.config import BusConfig
from eqgw.cluster.node import ClusterNode
from eqgw.cluster.settings import ClusterSettings


class _SlowIngest:
    """An ingest whose adding of a source waits until released (a loaded machine's reader
    start), so the takeover can be looked at half-way."""

    def __init__(self) -> None:
        self.adding = asyncio.Event()
        self.release = asyncio.Event()

    async def add_source(self, _src: Any) -> None:
        self.adding.set()
        await self.release.wait()


class _Commands:
    def add_writer(self, *_: Any) -> None:
        pass


def _owned_and_owners(node: ClusterNode) -> tuple[set[str], set[str]]:
    status = node.status()
    mine = {bus for bus, owner in status["owners"].items() if owner == node.instance_id}
    return set(status["owned"]), mine


async def test_a_bus_being_taken_is_owned_and_shown_with_its_owner_at_once() -> None:
    bus = BusConfig(name="B1", vehicle_id="V1", interface="virtual", channel="b1")
    ingest = _SlowIngest()
    node = ClusterNode(
        ClusterSettings(instance_id="gw-a"),
        "postgresql+psycopg://postgres@127.0.0.1:5432/test",  # not connected: no lease round
        [bus],
        ingest,  # type: ignore[arg-type]
        _Commands(),  # type: ignore[arg-type]
        make_source=lambda cfg: object(),  # type: ignore[arg-type,return-value]
    )
    assert _owned_and_owners(node) == (set(), set())
    take = asyncio.create_task(node._take("B1"))
    try:
        async with asyncio.timeout(10):
            await ingest.adding.wait()
        assert _owned_and_owners(node) == ({"B1"}, {"B1"})  # half-way: both, or neither
        ingest.release.set()
        async with asyncio.timeout(10):
            await take
        assert _owned_and_owners(node) == ({"B1"}, {"B1"})
    finally:
        take.cancel()
        await asyncio.gather(take, return_exceptions=True)
