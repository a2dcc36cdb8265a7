"""Asks every unit heard from whose series is unknown for its component and software ID."""

from __future__ import annotations

import asyncio
import logging
import time

from eqgw.commands.service import CommandRefused, CommandService, Submitter
from eqgw.describe import describe
from eqgw.ingest.events import UNIT_ONLINE, Event
from eqgw.ingest.hub import EventHub, SubscriberLagged
from eqgw.tasks import cancel_and_wait

log = logging.getLogger(__name__)

# The series decides which parameter writes a unit accepts and whether its voltages frame
# carries currents; the units only tell it when asked (PGN 59904 for 0xFEEB and 0xFEDA).
IDENTIFICATION = ("component_id", "software_id")
SYSTEM = Submitter(key_id=None, key_name="eqgw (identification)")
RETRY_S = 5.0  # after a request could not be queued (the database away)
NOT_HEARD_RETRY_S = 0.5  # a unit whose first frame was not yet one of its records
NOT_HEARD_TRIES = 20


class UnitIdentifier:
    """Queues identification requests through the command queue when a unit comes online."""

    def __init__(self, hub: EventHub, commands: CommandService) -> None:
        self.hub = hub
        self.commands = commands
        self.requested = 0
        self._task: asyncio.Task[None] | None = None
        self._retries: set[asyncio.Task[None]] = set()

    async def start(self) -> None:
        self._task = asyncio.create_task(self._run(), name="unit identification")

    async def stop(self) -> None:
        task, self._task = self._task, None
        for t in [task, *self._retries]:
            if t is not None:
                await cancel_and_wait(t)
        self._retries.clear()

    async def _run(self) -> None:
        first = True
        while True:
            with self.hub.subscribe([UNIT_ONLINE], maxsize=1000) as sub:
                if first:
                    # Units that came online before this subscribed (the gateway's start
                    # reads its buses first) published their event to nobody: ask them now.
                    first = False
                    for unit in self.commands.live.all_units():
                        await self.identify(Event(UNIT_ONLINE, unit.ref, time.time()))
                try:
                    async for event in sub:
                        await self.identify(event)
                except SubscriberLagged:
                    log.warning("identification fell behind unit-online events; resubscribing")
                    continue
            return

    async def identify(self, event: Event, tries: int = 0) -> None:
        """Request the IDs of the event's unit unless its series is already known."""
        unit = self.commands.live.get(event.unit.bus, event.unit.sa)
        if unit is None or unit.series is not None:
            return
        if event.unit.bus not in self.commands.writers:
            return  # another gateway owns this bus and will ask
        if unit.last_seen is None:
            # Its first frame was not a record of its own (a transport announcement): it
            # counts as heard from with its first record, and no new event comes then.
            if tries < NOT_HEARD_TRIES:
                self._again(event, NOT_HEARD_RETRY_S, tries + 1)
            return
        for what in IDENTIFICATION:
            try:
                await self.commands.submit(
                    "request",
                    event.unit.vehicle_id,
                    {"unit": event.unit.sa, "what": what},
                    SYSTEM,
                )
                self.requested += 1
            except CommandRefused as exc:
                # Offline again, or the same request still pending: the next online asks again.
                log.debug("no %s request for %s: %s", what, event.unit.key, exc.detail)
            except Exception as exc:  # the database away: ask again shortly, do not stop
                log.warning("no %s request for %s, asking again in %g s: %s",
                            what, event.unit.key, RETRY_S, describe(exc))  # fmt: skip
                self._again(event)
                return

    def _again(self, event: Event, delay: float = RETRY_S, tries: int = 0) -> None:
        """`identify(event)` again in `delay` s (a unit online stays online: no new event)."""

        async def later() -> None:
            await asyncio.sleep(delay)
            await self.identify(event, tries)

        task = asyncio.create_task(later(), name="unit identification retry")
        self._retries.add(task)
        task.add_done_callback(self._retries.discard)
