"""The alert engine: evaluates every rule on each unit as its data change, and on a tick.

It subscribes to the ingest hub, evaluates the units an event touched (from their live state,
not from the event: a resync after being dropped is the same evaluation for every unit),
persists raises and clears with their `alert_events` row in one transaction, and publishes
`alert_raised` / `alert_cleared` on the hub. A tick re-evaluates units whose delay or clear
delay is running, so a condition that holds while the unit goes quiet still fires. Open alerts
are loaded back at start, so a restart does not raise them again.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Concatenate

from sqlalchemy import Connection, Engine

from eqgw.alerts import repository as aq
from eqgw.alerts.config import resolve_rules
from eqgw.alerts.rules import Decision, Facts, Rule, RuleState
from eqgw.ingest import events
from eqgw.ingest.events import Event, UnitRef
from eqgw.ingest.hub import EventHub, SubscriberLagged, Subscription
from eqgw.ingest.state import LiveState, UnitState, VehicleStatus, vehicle_status
from eqgw.store.transaction import P, R, in_transaction
from eqgw.supervisor import Supervisor, spawn
from eqgw.tasks import cancel_and_wait, heals

if TYPE_CHECKING:
    from eqgw.config import Settings

log = logging.getLogger(__name__)

# What can change a verdict: value changes of the slots rules read, flags, faults, presence.
_KINDS = events.UNIT_KINDS
_SLOTS = frozenset(
    {"voltages", "battery_states/1", "battery_states/2", "battery_states/3", "battery_states/4"}
)
FULL_SWEEP_S = 30.0


def _relevant(event: Event) -> bool:
    return event.kind != events.LIVE or event.data.get("slot") in _SLOTS


def facts_of(st: UnitState, vehicle: VehicleStatus | None = None) -> Facts:
    """A unit's live state (and its vehicle's, when given) as rules see it."""
    return Facts(
        latest=st.latest,
        flags=st.status_flags,
        faults=frozenset(st.faults.open),
        online="OFFLINE" not in st.faults.open,
        vehicle_state=vehicle.state if vehicle is not None else None,
        vehicle_last_heard=vehicle.last_heard if vehicle is not None else None,
        vehicle_lead=vehicle is not None and vehicle.lead == st.ref.key,
    )


def rule_from_row(row: dict[str, Any]) -> Rule:
    return Rule(
        id=row["id"],
        kind=row["kind"],
        severity=row["severity"],
        enabled=bool(row["enabled"]),
        params=dict(row["params"] or {}),
        targets=tuple(row["targets"] or ()),
        description=row.get("description"),
        source=row.get("source", "api"),
    )


def rule_row(rule: Rule) -> dict[str, Any]:
    """A rule's database columns (without the times)."""
    return {
        "id": rule.id,
        "kind": rule.kind,
        "severity": rule.severity,
        "enabled": rule.enabled,
        "params": dict(rule.params),
        "targets": list(rule.targets),
        "description": rule.description,
        "source": rule.source,
    }


@dataclass(slots=True)
class EngineStats:
    evaluations: int = 0
    raised: int = 0
    cleared: int = 0
    resyncs: int = 0
    db_failures: int = 0

    def as_dict(self) -> dict[str, Any]:
        return {
            "evaluations": self.evaluations,
            "raised": self.raised,
            "cleared": self.cleared,
            "resyncs": self.resyncs,
            "db_failures": self.db_failures,
        }


class AlertEngine:
    """Rules x units -> alerts; call `start()`/`stop()` in the event loop that runs the hub."""

    def __init__(
        self,
        db: Engine,
        hub: EventHub,
        live: LiveState,
        settings: Settings,
        *,
        clock: Callable[[], float] | None = None,
        queue_size: int | None = None,
        owns: Callable[[str], bool] | None = None,
        supervisor: Supervisor | None = None,
    ) -> None:
        # Writes take SQLite's write lock up front (as the ingest writer does): a read that
        # upgrades to a write under live ingest would fail at once instead of waiting.
        self.db = db.execution_options(sqlite_begin="IMMEDIATE")
        self.hub = hub
        self.live = live
        self.settings = settings
        self.rules: dict[str, Rule] = {}
        self.states: dict[tuple[str, int], dict[str, RuleState]] = {}
        self.stats = EngineStats()
        # For /metrics: changes per (rule, severity), and each open alert's severity as raised.
        self.raised_by: Counter[tuple[str, str]] = Counter()
        self.cleared_by: Counter[tuple[str, str]] = Counter()
        self._severity: dict[int, str] = {}
        self.last_error: str | None = None
        self.last_error_at: float | None = None
        self._clock = clock or time.time
        # Several gateways on one database: each evaluates the buses it reads.
        self._owns = owns or (lambda _bus: True)
        self._queue_size = queue_size or settings.hub.subscriber_queue
        self._sub: Subscription | None = None
        # The gateway's: a failure that will not heal (a bug, storage gone for good) stops
        # the loop it happened in, reported failed (a fatal one ends the process).
        self.supervisor = supervisor
        self._tasks: list[asyncio.Task[None]] = []
        self._lock = asyncio.Lock()  # one evaluation at a time: events, ticks, reloads
        self._last_sweep = 0.0

    # -- life ------------------------------------------------------------------------------

    async def start(self, *, run: bool = True) -> None:
        """Sync the configured rules into the database, load rules and open alerts, subscribe;
        with `run`, also start the event and tick tasks (tests may drive `drain`/`tick`)."""
        configured = [rule_row(r) for r in resolve_rules(self.settings.alerts).values()]
        await asyncio.to_thread(self._in_tx, aq.sync_rules, configured, time.time())
        await self._load_rules()
        opened = await asyncio.to_thread(self._in_tx, aq.open_alerts)
        for alert in opened:
            state = self._state((alert["bus"], alert["sa"]), alert["rule"])
            state.opened(alert["id"])
            self._severity[alert["id"]] = alert["severity"]
        if opened:
            log.info("alerts: %d open alerts taken back", len(opened))
        self._sub = self._subscribe()
        if run:
            sup = self.supervisor
            self._tasks.append(spawn(sup, "alert engine", self._run, critical=False))
            self._tasks.append(spawn(sup, "alert tick", self._tick_loop, critical=False))

    async def stop(self) -> None:
        for task in self._tasks:
            await cancel_and_wait(task)
        self._tasks.clear()
        if self._sub is not None:
            self._sub.close()
            self._sub = None

    def _subscribe(self) -> Subscription:
        return self.hub.subscribe(_KINDS, maxsize=self._queue_size, predicate=_relevant)

    def _in_tx(
        self, fn: Callable[Concatenate[Connection, P], R], /, *args: P.args, **kwargs: P.kwargs
    ) -> R:
        return in_transaction(self.db, fn, *args, **kwargs)

    async def _load_rules(self) -> None:
        rows = await asyncio.to_thread(self._in_tx, aq.list_rules)
        self.rules = {r["id"]: rule_from_row(r) for r in rows}

    # -- the loops -------------------------------------------------------------------------

    async def _run(self) -> None:
        while True:
            sub = self._sub
            assert sub is not None
            try:
                first = await sub.get()
            except SubscriberLagged:
                await self.resync()
                continue
            except StopAsyncIteration:
                return  # the hub closed
            await self._handle([first, *self._drain_nowait(sub)])

    def _drain_nowait(self, sub: Subscription) -> list[Event]:
        out: list[Event] = []
        with contextlib.suppress(SubscriberLagged):  # noticed at the next get()
            while (ev := sub.get_nowait()) is not None:
                out.append(ev)
        return out

    async def _tick_loop(self) -> None:
        while True:
            await asyncio.sleep(self.settings.alerts.tick_s)
            try:
                await self.tick(self._clock())
            except Exception as exc:  # a database away: the next tick evaluates again
                self._failed(f"tick: {exc}")
                if not heals(exc):
                    raise  # a bug or storage gone for good: its supervisor says so
                log.warning("alert tick failed: %s", exc)

    async def drain(self) -> int:
        """Handle every event already queued (tests drive the engine with this); returns how
        many; resyncs when the subscription was dropped."""
        sub = self._sub
        assert sub is not None
        try:
            batch = self._drain_nowait(sub)
            if sub.lagged and sub.queue.empty():
                raise SubscriberLagged("dropped")
        except SubscriberLagged:
            await self.resync()
            return 0
        await self._handle(batch)
        return len(batch)

    async def _handle(self, batch: list[Event]) -> None:
        # A burst for one unit is one evaluation at its latest time.
        touched: dict[tuple[str, int], float] = {}
        for ev in batch:
            key = ev.unit.key
            touched[key] = max(touched.get(key, ev.ts), ev.ts)
        # Evaluated at the clock's now: a fault event carries the episode's last-seen time
        # (an OFFLINE episode starts at the last frame), but it is known only now.
        now = self._clock()
        async with self._lock:
            for key, ts in touched.items():
                st = self.live.get(*key)
                if st is not None:
                    await self._evaluate(st, max(ts, now))

    async def resync(self) -> None:
        """After being dropped by the hub: subscribe again and evaluate every unit."""
        self.stats.resyncs += 1
        log.warning("alert engine fell behind the hub; resynchronising from live state")
        if self._sub is not None:
            self._sub.close()
        self._sub = self._subscribe()
        await self.evaluate_all(self._clock())

    async def tick(self, now: float) -> None:
        """Time passes: units with a running delay (and every unit now and then) again."""
        full = now - self._last_sweep >= FULL_SWEEP_S or now < self._last_sweep
        if full:
            self._last_sweep = now
        async with self._lock:
            for st in self.live.all_units():
                states = self.states.get(st.ref.key)
                waiting = states is not None and any(
                    s.pending_since is not None or s.clearing_since is not None
                    for s in states.values()
                )
                if full or waiting:
                    await self._evaluate(st, now)

    async def evaluate_all(self, now: float) -> None:
        async with self._lock:
            for st in self.live.all_units():
                await self._evaluate(st, now)

    # -- evaluation ------------------------------------------------------------------------

    def _state(self, key: tuple[str, int], rule_id: str) -> RuleState:
        per_unit = self.states.get(key)
        if per_unit is None:
            per_unit = self.states[key] = {}
        state = per_unit.get(rule_id)
        if state is None:
            state = per_unit[rule_id] = RuleState()
        return state

    async def _evaluate(self, st: UnitState, now: float) -> None:
        if not self._owns(st.ref.bus):
            return
        vehicle = vehicle_status(
            self.live.of_vehicle(st.ref.vehicle_id),
            now,
            self.settings.monitor.not_reporting_after_s,
        )
        facts = facts_of(st, vehicle)
        key = st.ref.key
        for rule in list(self.rules.values()):
            if not rule.enabled:
                continue
            self.stats.evaluations += 1
            state = self._state(key, rule.id)
            try:
                obs = rule.observe(facts)
            except (KeyError, TypeError, ValueError) as exc:
                log.warning("rule %s cannot be evaluated: %s", rule.id, exc)
                continue
            decision = state.step(obs.verdict, now, rule.delay_s, rule.clear_delay_s)
            if decision is Decision.RAISE:
                await self._raise(st.ref, rule, state, obs.message, obs.values, now)
            elif decision is Decision.CLEAR and state.alert_id is not None:
                await self._clear(st.ref, state, now, "condition")
            elif decision is Decision.CLEAR:
                state.closed()

    async def _raise(
        self,
        ref: UnitRef,
        rule: Rule,
        state: RuleState,
        message: str,
        values: dict[str, Any],
        ts: float,
    ) -> None:
        def write() -> tuple[dict[str, Any], bool]:
            with self.db.begin() as conn:
                muted = aq.is_muted(conn, ref.vehicle_id, rule.id, time.time())
                return aq.raise_alert(
                    conn,
                    vehicle_id=ref.vehicle_id,
                    bus=ref.bus,
                    sa=ref.sa,
                    rule=rule.id,
                    severity=rule.severity,
                    message=message,
                    values=values,
                    ts=ts,
                    muted=muted,
                )

        try:
            alert, created = await asyncio.to_thread(write)
        except Exception as exc:  # the database may be away: the next evaluation retries
            self.stats.db_failures += 1
            self._failed(f"raising {rule.id} on {ref.bus}/{ref.sa}: {exc}")
            if not heals(exc):
                raise
            log.warning("raising alert %s on %s/%s failed: %s", rule.id, ref.bus, ref.sa, exc)
            return
        state.opened(alert["id"])
        self._severity[alert["id"]] = alert["severity"]
        if created:
            self.stats.raised += 1
            self.raised_by[rule.id, alert["severity"]] += 1
            self.hub.publish(Event(events.ALERT_RAISED, ref, ts, alert))

    async def _clear(self, ref: UnitRef, state: RuleState, ts: float, by: str) -> None:
        alert_id = state.alert_id
        assert alert_id is not None
        try:
            alert = await asyncio.to_thread(self._in_tx, aq.clear_alert, alert_id, ts=ts, by=by)
        except Exception as exc:  # the database may be away: the next evaluation retries
            self.stats.db_failures += 1
            self._failed(f"clearing alert {alert_id}: {exc}")
            if not heals(exc):
                raise
            log.warning("clearing alert %s failed: %s", alert_id, exc)
            return
        state.closed()
        self._severity.pop(alert_id, None)
        if alert is not None:
            self._count_cleared(alert)
            self.hub.publish(Event(events.ALERT_CLEARED, ref, ts, alert))

    # -- rule changes (from the API) --------------------------------------------------------

    async def rules_changed(self) -> None:
        """Reload the rules; alerts of a rule now disabled or deleted are cleared."""
        async with self._lock:
            await self._load_rules()
            now = self._clock()
            for key, per_unit in self.states.items():
                for rule_id, state in list(per_unit.items()):
                    rule = self.rules.get(rule_id)
                    if rule is not None and rule.enabled:
                        continue
                    if state.alert_id is not None:
                        st = self.live.get(*key)
                        ref = st.ref if st is not None else None
                        by = "rule_deleted" if rule is None else "rule_disabled"
                        await self._clear_any(key, ref, state, now, by)
                    else:
                        state.closed()
        await self.evaluate_all(self._clock())

    async def _clear_any(
        self, key: tuple[str, int], ref: UnitRef | None, state: RuleState, ts: float, by: str
    ) -> None:
        if ref is not None:
            await self._clear(ref, state, ts, by)
            return
        # A unit not in live state (its bus left the configuration): clear without its ref.
        alert_id = state.alert_id
        assert alert_id is not None
        alert = await asyncio.to_thread(self._in_tx, aq.clear_alert, alert_id, ts=ts, by=by)
        state.closed()
        self._severity.pop(alert_id, None)
        if alert is not None:
            self._count_cleared(alert)
            ref = UnitRef(alert["vehicle_id"], key[0], key[1])
            self.hub.publish(Event(events.ALERT_CLEARED, ref, ts, alert))

    def _count_cleared(self, alert: dict[str, Any]) -> None:
        self.stats.cleared += 1
        self.cleared_by[alert["rule"], alert["severity"]] += 1

    def _failed(self, error: str) -> None:
        self.last_error, self.last_error_at = error[:500], time.time()

    @property
    def running(self) -> bool:
        """The event and tick tasks are alive (False before `start`, after `stop`, or when
        one ended on an unexpected error)."""
        return bool(self._tasks) and not any(t.done() for t in self._tasks)

    def open_by_severity(self) -> Counter[str]:
        """Open alerts of the units this engine evaluates, by the severity they were raised
        with (a rule's severity changed later does not move its open alerts)."""
        out: Counter[str] = Counter()
        for per_unit in self.states.values():
            for rule_id, s in per_unit.items():
                if not s.open:
                    continue
                sev = self._severity.get(s.alert_id) if s.alert_id is not None else None
                rule = self.rules.get(rule_id)
                out[sev or (rule.severity if rule is not None else "unknown")] += 1
        return out

    def status(self) -> dict[str, Any]:
        error = self.last_error
        for task in self._tasks:  # a loop that died says why
            if task.done() and not task.cancelled() and task.exception() is not None:
                error = f"{task.get_name()} stopped: {task.exception()!r}"[:500]
        sub = self._sub
        return {
            **self.stats.as_dict(),
            "rules": len(self.rules),
            "open": sum(self.open_by_severity().values()),
            "running": self.running,
            # Events the engine has been given but not yet evaluated (its lag, in events).
            "backlog": sub.queue.qsize() if sub is not None else 0,
            "last_error": error,
            "last_error_at": self.last_error_at,
        }


def ingest_clock(pipeline: Any) -> Callable[[], float]:
    """Frame time now: the pipeline's clock advanced by the wall time since it last moved
    (as the ingest's monitors do), so delays run in the data's time and through silence."""
    last = [float("-inf"), time.monotonic()]

    def now() -> float:
        clock = pipeline.clock
        mono = time.monotonic()
        if clock == float("-inf"):
            return time.time()
        if clock != last[0]:
            last[0], last[1] = clock, mono
        return float(clock) + (mono - last[1])

    return now


async def start_alert_engine(settings: Settings, db: Engine, ingest: Any) -> AlertEngine | None:
    """The engine of a running gateway (None when `alerts.enabled` is false), started on the
    ingest's hub and live state, evaluating only the buses this gateway reads."""
    if not settings.alerts.enabled:
        return None
    pipeline = ingest.pipeline

    def owns(bus: str) -> bool:
        # Its own buses, and edge-forwarded ones shown in its live view (uploaded to it).
        active = pipeline.active
        return active is None or bus in active or bus in ingest.live.attached

    engine = AlertEngine(
        db,
        ingest.hub,
        ingest.live,
        settings,
        clock=ingest_clock(pipeline),
        owns=owns,
        supervisor=ingest.supervisor,
    )
    await engine.start()
    return engine
