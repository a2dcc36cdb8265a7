"""The gateway's partition keeper: a supervised task that makes the time partitions ahead
(eqgw.store.partitions.maintain), hourly, on PostgreSQL only. Several gateways may run one
each: a PostgreSQL advisory lock lets one of them work at a time, the others skip their
round."""

from __future__ import annotations

import asyncio
import logging
import threading
from types import TracebackType
from typing import TYPE_CHECKING

from sqlalchemy import Engine

from eqgw.store.engine import deadline_left
from eqgw.store.partitions import MaintainResult, maintain
from eqgw.tasks import cancel_and_wait

if TYPE_CHECKING:  # the settings' root imports no subsystem (tests/test_import_cycles.py)
    from eqgw.config import RetentionSettings
    from eqgw.supervisor import Supervisor

log = logging.getLogger(__name__)

TASK_NAME = "storage partitions"
# How long a stop waits for a round's thread to end (it ends after the partition at hand).
ROUND_STOP_S = 1.0


class PartitionKeeper:
    """`async with PartitionKeeper(engine, settings.retention, supervisor):` runs the keeper
    as the supervised task `storage partitions` (its state in /readyz and /metrics like every
    task's) for the block's duration; nothing on SQLite."""

    def __init__(
        self,
        engine: Engine,
        retention: RetentionSettings,
        supervisor: Supervisor,
        *,
        interval_s: float | None = None,
    ) -> None:
        self.engine = engine
        self.retention = retention
        self.supervisor = supervisor
        self.interval_s = retention.interval_s if interval_s is None else interval_s
        self.last: MaintainResult | None = None
        self._task: asyncio.Task[None] | None = None
        # The round in its thread: a cancel does not stop a thread, so the stop tells it to end
        # after its current partition and waits for it (its connection goes back to the
        # engine's pool before the lifespan disposes of the engine).
        self._round: asyncio.Future[MaintainResult] | None = None
        self._stopping = threading.Event()

    async def __aenter__(self) -> PartitionKeeper:
        if self.engine.dialect.name == "postgresql":
            # The first round before the ingest starts writing: a partition made for a range
            # while a write routes a row there can fail that write ("violates partition
            # constraint" on the default partition, which the row was routed to before the
            # new partition existed). Made days ahead, later rounds never make one for now.
            try:
                self.last = await asyncio.to_thread(self.round)
            except Exception as exc:  # the task's own rounds retry and report it
                log.warning("partitions: the first round failed (%s); retrying in the task", exc)
            self._task = self.supervisor.start(TASK_NAME, self.run)
        return self

    async def __aexit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self._stopping.set()
        if self._task is not None:
            await cancel_and_wait(self._task)
            self._task = None
        if self._round is not None:
            if not self._round.done():
                # Briefly, and never past the shutdown's database deadline: the writer's
                # final flush comes after this and needs the time more.
                left = deadline_left()
                wait = ROUND_STOP_S if left is None else min(ROUND_STOP_S, left)
                await asyncio.wait({self._round}, timeout=wait)
            if self._round.done() and not self._round.cancelled():
                self._round.exception()  # seen (its task reported it, or it was cut short)

    def round(self) -> MaintainResult:
        """One maintenance round (blocking: run it in a thread)."""
        r = self.retention
        return maintain(
            self.engine,
            raw_days=r.raw_days,
            rollup_days=r.rollup_days_by_width(),
            ahead_days=r.partitions_ahead_days,
            stop=self._stopping,
            adopt=False,  # moves under live readers: left to `eqgw db prune` (partitions.py)
        )

    async def run(self) -> None:
        """A round at once, then every `interval_s`. A failed round (the database away, a
        lock not granted in time) raises: the supervisor reports the task backing off
        (/readyz, /metrics) and starts it again after its backoff; a fault that will not heal
        ends the process."""
        if self.last is not None:  # the first round ran at the start
            await asyncio.sleep(self.interval_s)
        while True:
            self._round = asyncio.ensure_future(asyncio.to_thread(self.round))
            self.last = await asyncio.shield(self._round)
            if self.last.made:
                log.info(
                    "partitions: made %d (%d rows moved from default partitions)",
                    len(self.last.made),
                    self.last.moved,
                )
            await asyncio.sleep(self.interval_s)
