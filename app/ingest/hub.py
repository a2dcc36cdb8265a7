"""In-process publish/subscribe of ingest events; a slow subscriber never blocks the ingest."""

from __future__ import annotations

import asyncio
from collections.abc import Callable, Iterable
from dataclasses import dataclass

from eqgw.ingest.events import KINDS, Event


class SubscriberLagged(Exception):
    """The subscriber fell a whole queue behind and was dropped; resubscribe and resync."""


@dataclass(slots=True)
class HubStats:
    """Counters of the hub."""

    published: int = 0
    delivered: int = 0
    dropped_subscribers: int = 0


class Subscription:
    """One subscriber's bounded queue; iterate it with `async for event in subscription`."""

    def __init__(
        self,
        hub: EventHub,
        kinds: frozenset[str] | None,
        maxsize: int,
        predicate: Callable[[Event], bool] | None,
    ) -> None:
        self._hub = hub
        self.kinds = kinds
        self.predicate = predicate
        self.queue: asyncio.Queue[Event | None] = asyncio.Queue(maxsize)
        self.lagged = False
        self.closed = False
        self.received = 0

    def wants(self, event: Event) -> bool:
        if self.kinds is not None and event.kind not in self.kinds:
            return False
        return self.predicate is None or self.predicate(event)

    async def get(self) -> Event:
        """The next event; raises SubscriberLagged once a dropped subscriber has drained."""
        if self.closed and self.queue.empty():
            raise self._end()
        event = await self.queue.get()
        if event is None:
            raise self._end()
        return event

    def get_nowait(self) -> Event | None:
        """The next event if one is queued, else None (also once closed and drained)."""
        try:
            event = self.queue.get_nowait()
        except asyncio.QueueEmpty:
            event = None
        if event is None and self.lagged:
            raise SubscriberLagged("subscriber dropped: queue overflowed")
        return event

    def _end(self) -> Exception:
        if self.lagged:
            return SubscriberLagged("subscriber dropped: queue overflowed")
        return StopAsyncIteration()

    def __aiter__(self) -> Subscription:
        return self

    async def __anext__(self) -> Event:
        return await self.get()

    def close(self) -> None:
        """Stop receiving; pending events can still be read."""
        self._hub._remove(self)
        if not self.closed:
            self.closed = True
            self._wake()

    def _wake(self) -> None:
        # A waiting consumer must see the end; make room for the sentinel if needed.
        if self.queue.full():
            self.queue.get_nowait()
        self.queue.put_nowait(None)

    def __enter__(self) -> Subscription:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class EventHub:
    """Fan-out of events to subscribers; call `publish` from the event loop's thread only."""

    def __init__(self, default_maxsize: int = 10_000) -> None:
        self.default_maxsize = default_maxsize
        self._subs: list[Subscription] = []
        self._kinds_wanted: set[str] = set()
        self.stats = HubStats()

    def subscribe(
        self,
        kinds: Iterable[str] | None = None,
        *,
        maxsize: int | None = None,
        predicate: Callable[[Event], bool] | None = None,
    ) -> Subscription:
        """A new subscription to `kinds` (all when None), optionally filtered by `predicate`."""
        wanted = frozenset(kinds) if kinds is not None else None
        if wanted is not None and not wanted <= KINDS:
            raise ValueError(f"unknown event kinds: {sorted(wanted - KINDS)}")
        sub = Subscription(self, wanted, maxsize or self.default_maxsize, predicate)
        self._subs.append(sub)
        self._refresh()
        return sub

    def wants(self, kind: str) -> bool:
        """Whether anyone listens to `kind`: lets the ingest skip building unused events."""
        return kind in self._kinds_wanted

    @property
    def subscribers(self) -> int:
        return len(self._subs)

    def publish(self, event: Event) -> None:
        """Deliver to every interested subscriber without waiting; drop the ones that are full."""
        self.stats.published += 1
        for sub in list(self._subs):
            if not sub.wants(event):
                continue
            try:
                sub.queue.put_nowait(event)
                self.stats.delivered += 1
            except asyncio.QueueFull:
                sub.lagged = True
                sub.closed = True
                self._remove(sub)
                self.stats.dropped_subscribers += 1
                sub._wake()

    def close(self) -> None:
        """End every subscription (at shutdown)."""
        for sub in list(self._subs):
            sub.close()

    def _remove(self, sub: Subscription) -> None:
        if sub in self._subs:
            self._subs.remove(sub)
            self._refresh()

    def _refresh(self) -> None:
        kinds: set[str] = set()
        for sub in self._subs:
            kinds |= sub.kinds if sub.kinds is not None else KINDS
        self._kinds_wanted = kinds
