"""Asks every unit heard from whose series is unknown for its component and software ID."""

from __future__ import annotations

import asyncio
import logging
import time
from dataclasses import dataclass

from eqgw.commands.model import CommandKind
from eqgw.commands.service import CommandService
from eqgw.commands.validation import CommandRefused, Submitter
from eqgw.describe import describe
from eqgw.ingest.events import UNIT_ONLINE
from eqgw.ingest.faults import OFFLINE
from eqgw.ingest.hub import EventHub, SubscriberLagged, Subscription
from eqgw.ingest.state import UnitState
from eqgw.supervisor import Supervisor
from eqgw.tasks import cancel_and_wait, heals

log = logging.getLogger(__name__)

# The series decides which parameter writes a unit accepts and whether its voltages frame
# carries currents; the units only tell it when asked (PGN 59904 for 0xFEEB and 0xFEDA).
IDENTIFICATION = ("component_id", "software_id")
SYSTEM = Submitter(key_id=None, key_name="eqgw (identification)")
RETRY_S = 5.0  # after a request could not be queued (the database away)
# Every unit without a series is looked for this often, besides at once when one comes online.
SCAN_S = 5.0
# A unit asked and still without a series is asked again after this, then twice as long each
# time up to MAX_ASK_AGAIN_S (an unanswered request ends within the command expiry, 30 s).
ASK_AGAIN_S = 30.0
MAX_ASK_AGAIN_S = 600.0


@dataclass(slots=True)
class _Asked:
    due: float  # monotonic: when the unit is asked again if it still has no series
    delay: float  # the wait after the next ask


class UnitIdentifier:
    """Queues identification requests through the command queue for every online unit of a
    bus this gateway writes to whose series is unknown: at once when a unit comes online, and
    on a periodic scan of the live state (units heard before this started, restored from the
    database, or whose answer never came), each unit again with a doubling backoff."""

    def __init__(
        self,
        hub: EventHub,
        commands: CommandService,
        *,
        scan_s: float = SCAN_S,
        ask_again_s: float = ASK_AGAIN_S,
        max_ask_again_s: float = MAX_ASK_AGAIN_S,
        supervisor: Supervisor | None = None,
    ) -> None:
        self.hub = hub
        self.commands = commands
        self.scan_s = scan_s
        self.ask_again_s = ask_again_s
        self.max_ask_again_s = max(max_ask_again_s, ask_again_s)
        self.requested = 0
        self._asked: dict[tuple[str, int], _Asked] = {}
        self._supervisor = supervisor
        self._task: asyncio.Task[None] | None = None

    async def start(self) -> None:
        if self._supervisor is not None:
            self._task = self._supervisor.start("unit identification", self._run)
        else:
            self._task = asyncio.create_task(self._run(), name="unit identification")

    async def stop(self) -> None:
        task, self._task = self._task, None
        if task is not None:
            await cancel_and_wait(task)

    async def _run(self) -> None:
        while True:
            # Subscribed before the first scan: a unit is either in the live state already
            # or its online event wakes the next scan.
            with self.hub.subscribe([UNIT_ONLINE], maxsize=1000) as sub:
                try:
                    while True:
                        await self.scan()
                        if not await self._wait(sub):
                            return
                except SubscriberLagged:
                    log.warning("identification fell behind unit-online events; resubscribing")

    async def _wait(self, sub: Subscription) -> bool:
        """Until a unit comes online or the scan period ends; False once the hub closed."""
        try:
            async with asyncio.timeout(self.scan_s):
                await sub.get()
        except TimeoutError:
            return True
        except StopAsyncIteration:
            return False
        while sub.get_nowait() is not None:
            pass  # one scan covers every unit that came online meanwhile
        return True

    def _wanted(self, st: UnitState) -> bool:
        """Whether this gateway should ask `st` now (see `scan`)."""
        if st.series is not None:
            return False
        if st.ref.bus not in self.commands.writers:
            return False  # another gateway owns this bus and will ask
        return OFFLINE not in st.faults.open and st.last_seen is not None

    async def scan(self) -> None:
        """Ask every unit that has no series and is due; forget units that have one."""
        asked = self._asked
        for key in list(asked):
            known = self.commands.live.get(*key)
            if known is None or known.series is not None:
                del asked[key]
        for st in self.commands.live.all_units():
            if not self._wanted(st):
                continue
            key = (st.ref.bus, st.ref.sa)
            prev = asked.get(key)
            now = time.monotonic()
            if prev is not None and now < prev.due:
                continue
            delay = self.ask_again_s if prev is None else prev.delay
            if not await self._ask(st):
                # The database away: this unit shortly, the others on a later scan.
                asked[key] = _Asked(time.monotonic() + RETRY_S, delay)
                return
            asked[key] = _Asked(time.monotonic() + delay, min(delay * 2, self.max_ask_again_s))

    async def _ask(self, st: UnitState) -> bool:
        """Queue the unit's identification requests; False if the database refused them."""
        ref = st.ref
        for what in IDENTIFICATION:
            try:
                await self.commands.submit(
                    CommandKind.REQUEST, ref.vehicle_id, {"unit": ref.sa, "what": what}, SYSTEM
                )
                self.requested += 1
            except CommandRefused as exc:
                # Offline again, or the same request still pending: asked again later.
                log.debug("no %s request for %s: %s", what, ref.key, exc.detail)
            except Exception as exc:  # the database away: ask again shortly, do not stop
                if not heals(exc):
                    raise  # a bug or storage gone for good: its supervisor says so
                log.warning(
                    "no %s request for %s, asking again in %g s: %s",
                    what,
                    ref.key,
                    RETRY_S,
                    describe(exc),
                )
                return False
        return True
