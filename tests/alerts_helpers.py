"""A deterministic alerting rig: simulated fleet on a manual clock -> pipeline -> alert engine."""

from __future__ import annotations

from typing import Any

import can
from sqlalchemy import Engine, select

from eqgw.alerts.engine import AlertEngine
from eqgw.config import Settings
from eqgw.ingest.hub import EventHub
from eqgw.ingest.pipeline import IngestPipeline
from eqgw.sim.clock import ManualClock
from eqgw.sim.fleet import SimulatedFleet
from eqgw.store.models import Alert, AlertEvent
from eqgw.store.writes import ensure_vehicles

EPOCH = 1_700_000_000.0


class Rig:
    """The fleet's frames fed step by step into a pipeline whose hub the engine reads."""

    def __init__(
        self,
        db: Engine,
        vehicles: int = 0,
        *,
        scenario: str | None = None,
        alerts: dict[str, Any] | None = None,
        monitor: dict[str, Any] | None = None,
        hub_queue: int = 10_000,
        background_traffic: bool = False,
    ) -> None:
        self.clock = ManualClock(EPOCH)
        self.fleet = SimulatedFleet(
            vehicles or None,
            scenario=scenario,
            clock=self.clock,
            seed=1,
            background_traffic=background_traffic,
        )
        names = self.fleet.names
        self.settings = Settings(
            database_url=str(db.url),
            vehicles=[{"id": n, "name": f"{n} coach"} for n in names],
            buses=[
                {
                    "name": n,
                    "vehicle_id": n,
                    "interface": "virtual",
                    "channel": self.fleet.channels[n],
                    "equalizer_sas": [u.sa for u in self.fleet.vehicle(n).spec.units],
                }
                for n in names
            ],
            alerts=alerts or {},
            monitor=monitor or {},
        )
        self.db = db
        self.hub = EventHub(hub_queue)
        self.pipeline = IngestPipeline.from_settings(self.settings, self.hub)
        self.engine = AlertEngine(
            db,
            self.hub,
            self.pipeline.live,
            self.settings,
            clock=self.clock.now,
            queue_size=hub_queue,
        )
        self._frames: list[can.Message] = []
        for n in names:
            self.fleet.add_tap(n, lambda m, n=n: self._frames.append(_on(m, n)))
        with db.begin() as conn:
            ensure_vehicles(
                conn, [{"id": n, "name": f"{n} coach", "depot": None} for n in names], True
            )

    async def start(self) -> None:
        await self.engine.start(run=False)
        self.fleet.open()

    async def stop(self) -> None:
        await self.engine.stop()
        self.fleet.close()

    async def run(self, seconds: float, step: float = 1.0, each: Any = None) -> None:
        """Advance the fleet by `seconds` in steps; after each, ingest and evaluate."""
        end = self.clock.now() + seconds
        while self.clock.now() < end - 1e-9:
            now = self.fleet.advance(min(step, end - self.clock.now()))
            frames, self._frames = self._frames, []
            self.pipeline.process_many(frames)
            self.pipeline.tick(now)
            self.pipeline.take_rows()
            await self.engine.drain()
            await self.engine.tick(now)
            if each is not None:
                each(now)

    def alerts(self, rule: str | None = None) -> list[dict[str, Any]]:
        with self.db.connect() as conn:
            stmt = select(Alert.__table__).order_by(Alert.id)
            if rule is not None:
                stmt = stmt.where(Alert.__table__.c.rule == rule)
            return [dict(r._mapping) for r in conn.execute(stmt)]

    def events(self) -> list[dict[str, Any]]:
        with self.db.connect() as conn:
            rows = conn.execute(select(AlertEvent.__table__).order_by(AlertEvent.id))
            return [dict(r._mapping) for r in rows]


def _on(msg: can.Message, bus: str) -> can.Message:
    return can.Message(
        timestamp=msg.timestamp,
        arbitration_id=msg.arbitration_id,
        data=bytes(msg.data),
        is_extended_id=msg.is_extended_id,
        channel=bus,
    )
