"""A restarted gateway takes back the persisted live state and the open fault episodes."""

from __future__ import annotations

import asyncio
from collections.abc import Callable
from typing import Any

import can
from sqlalchemy import text

from eqgw.config import Settings
from eqgw.ingest import events
from eqgw.ingest.faults import HEARTBEAT_STUCK, FaultTracker
from eqgw.ingest.service import IngestService
from eqgw.protocol.encode import encode
from tests.bus_helpers import within

BUS = "B/can0"
OVF = {"spn": 168, "fmi": 0, "oc": 3, "cm": 0}
LAMPS = {"mil": 0, "rsl": 0, "awl": 1, "pl": 0}


class QueueSource:
    """A frame source the test feeds batch by batch."""

    def __init__(self, name: str) -> None:
        self.name = name
        self.queue: asyncio.Queue[list[can.Message]] = asyncio.Queue()

    async def start(self) -> None:
        return None

    async def stop(self, timeout: float = 10.0) -> None:
        self.queue.put_nowait([])

    async def get_batch(self, max_frames: int = 1000) -> list[can.Message]:
        return await self.queue.get()

    def status(self) -> dict[str, Any]:
        return {"name": self.name}


def _msgs(ts: float, name: str, fields: dict[str, Any]) -> list[can.Message]:
    return [
        can.Message(timestamp=ts, arbitration_id=can_id, data=data, channel=BUS)
        for can_id, data in encode(name, fields, sa=30)
    ]


def _settings(url: str) -> Settings:
    return Settings(
        database_url=url,
        buses=[{"name": BUS, "vehicle_id": "B", "interface": "virtual", "channel": "x"}],
        vehicles=[{"id": "B"}],
        # Wall time between the test's steps must not make the unit offline or its DM1 stale.
        monitor={"offline_after_s": 3600, "dm1_stale_after_s": 3600},
    )


async def _until(cond: Callable[[], bool], what: str) -> None:
    async def wait() -> None:
        while not cond():
            await asyncio.sleep(0.02)

    try:
        await within(wait(), 60)
    except TimeoutError:
        raise AssertionError(f"timed out waiting for {what}") from None


async def _feed(svc: IngestService, src: QueueSource, msgs: list[can.Message]) -> None:
    target = svc.pipeline.stats.frames + len(msgs)
    src.queue.put_nowait(msgs)
    await _until(lambda: svc.pipeline.stats.frames >= target, "frames processed")


def _episodes(url: str) -> list[tuple[Any, ...]]:
    from eqgw.store.engine import create_engine

    engine = create_engine(url)
    try:
        with engine.connect() as conn:
            return [
                tuple(r)
                for r in conn.execute(
                    text(
                        "SELECT fault, state, started_at, ended_at, ended_by FROM fault_episodes "
                        "ORDER BY fault, started_at"
                    )
                )
            ]
    finally:
        engine.dispose()


async def test_restart_continues_open_episodes_and_shows_live_values(db_url: str) -> None:
    settings = _settings(db_url)
    src = QueueSource(BUS)
    svc = IngestService(settings, sources=[src], retention=False)
    await svc.start()
    try:
        await _feed(
            svc,
            src,
            _msgs(1000.0, "status", {"imb": "active"})
            + _msgs(1000.0, "dm1", {"lamps": LAMPS, "dtcs": [OVF]})
            + _msgs(1000.0, "voltages", {"v12": 12.5, "v24": 25.0, "i12": 1.0, "i24": 2.0})
            + _msgs(1001.0, "voltages", {"v12": 12.75, "v24": 25.5, "i12": 1.0, "i24": 2.0}),
        )
    finally:
        assert await svc.stop() == 0
    assert _episodes(db_url) == [
        ("IMB", "active", 1000.0, None, None),
        ("OVF", "active", 1000.0, None, None),
    ]

    # The restarted gateway knows the unit, its values and its open faults before any frame.
    src = QueueSource(BUS)
    svc = IngestService(settings, sources=[src], retention=False)
    opened = svc.hub.subscribe({events.FAULT_OPEN})
    await svc.start()
    try:
        (unit,) = svc.live.snapshot("B")
        assert unit["latest"]["voltages"]["ts"] == 1001.0
        assert unit["latest"]["voltages"]["fields"]["v12"] == 12.75
        assert unit["last_seen"] == 1001.0
        assert unit["online"] is True
        assert {f["fault"]: f["state"] for f in unit["faults"]} == {
            "IMB": "active",
            "OVF": "active",
        }
        # The same faults still reported: the episodes continue, none is opened again.
        await _feed(
            svc,
            src,
            _msgs(1003.0, "status", {"imb": "active"})
            + _msgs(1003.0, "dm1", {"lamps": LAMPS, "dtcs": [OVF]}),
        )
        assert opened.queue.empty()
        # Then they clear: the original episodes close.
        await _feed(
            svc,
            src,
            _msgs(1004.0, "status", {"imb": "inactive"})
            + _msgs(1004.0, "dm1", {"lamps": LAMPS, "dtcs": []}),
        )
        assert svc.live.snapshot("B")[0]["faults"] == []
    finally:
        assert await svc.stop() == 0
    assert _episodes(db_url) == [
        ("IMB", "closed", 1000.0, 1004.0, "status"),
        ("OVF", "closed", 1000.0, 1004.0, "dm1_all_clear"),
    ]


def test_restored_stale_episode_becomes_active_again_without_a_new_one() -> None:
    t = FaultTracker(dm1_stale_after_s=5.0)
    row = {
        "fault": "OVF",
        "started_at": 10.0,
        "last_seen_at": 12.0,
        "source": "dm1",
        "state": "stale",
        "occurrence_count": 3,
        "spn": 168,
        "fmi": 0,
    }
    t.restore([row], last_frame=20.0, heartbeat=None)
    assert t.tick(25.0) == []  # already stale; the unit's last frame was 5 s ago
    ((kind, ep),) = t.on_dm1(26.0, {"lamps": LAMPS, "dtcs": [{**OVF, "code": "OVF"}]})
    assert (kind, ep.started_at, ep.state) == (events.FAULT_UPDATE, 10.0, "active")


def test_restored_stuck_heartbeat_stays_stuck_until_it_changes() -> None:
    t = FaultTracker(heartbeat_stuck_after=3)
    row = {
        "fault": HEARTBEAT_STUCK,
        "started_at": 10.0,
        "last_seen_at": 12.0,
        "source": "monitor",
        "state": "active",
    }
    t.restore([row], last_frame=12.0, heartbeat=1)
    assert t.on_heartbeat(13.0, 1) == []
    assert t.open[HEARTBEAT_STUCK].last_seen_at == 13.0
    ((kind, ep),) = t.on_heartbeat(14.0, 2)
    assert (kind, ep.started_at, ep.ended_by) == (events.FAULT_CLOSE, 10.0, "heartbeat")


class OpeningSource(QueueSource):
    """A frame source whose bus opens when the test says (a BusReader's `state`)."""

    def __init__(self, name: str) -> None:
        super().__init__(name)
        self.state = "connecting"


async def test_restart_does_not_page_units_whose_bus_is_not_open_yet(db_url: str) -> None:
    """Two buses, one unit each; a restart after longer than the offline window. The first
    bus back delivers frames at once, the second opens later: its unit is not offline
    meanwhile (nothing was heard from a bus not open). Once open, a unit silent for the
    offline window is offline as before."""
    import time

    buses = ["A/can0", "B/can0"]
    settings = Settings(
        database_url=db_url,
        buses=[
            {"name": b, "vehicle_id": b[0], "interface": "virtual", "channel": b} for b in buses
        ],
        vehicles=[{"id": "A"}, {"id": "B"}],
        monitor={"offline_after_s": 1.0, "dm1_stale_after_s": 3600},
    )

    def frames(bus: str, ts: float) -> list[can.Message]:
        fields = {"v12": 12.5, "v24": 25.0, "i12": 1.0, "i24": 2.0}
        return [
            can.Message(timestamp=ts, arbitration_id=can_id, data=data, channel=bus)
            for can_id, data in encode("voltages", fields, sa=30)
        ]

    srcs = [OpeningSource(b) for b in buses]
    svc = IngestService(settings, sources=srcs, retention=False)
    await svc.start()
    try:
        for src in srcs:
            src.state = "open"
            # Heard 1.5 s ago: the restart takes longer than the offline window.
            await _feed(svc, src, frames(src.name, time.time() - 1.5))
    finally:
        assert await svc.stop() == 0

    a, b = (OpeningSource(name) for name in buses)
    svc = IngestService(settings, sources=[a, b], retention=False)
    opened = svc.hub.subscribe({events.FAULT_OPEN})
    await svc.start()
    try:
        a.state = "open"
        for _ in range(12):  # A's unit keeps talking for 2.4 s, B's bus is still connecting
            await _feed(svc, a, frames(a.name, time.time()))
            await asyncio.sleep(0.2)
        offline = []
        while not opened.queue.empty():
            offline.append(opened.queue.get_nowait())
        assert offline == []
        assert {u["bus"]: u["online"] for u in svc.live.snapshot()} == {
            "A/can0": True,
            "B/can0": True,
        }
        # B's bus opens and its unit says nothing: offline after the window.
        b.state = "open"
        await _until(
            lambda: {u["bus"]: u["online"] for u in svc.live.snapshot()}["B/can0"] is False,
            "B's silent unit offline once its bus is open",
        )
    finally:
        assert await svc.stop() == 0


class FailingOnceSource(QueueSource):
    """A frame source whose first read fails (a driver error escaping the reader)."""

    def __init__(self, name: str) -> None:
        super().__init__(name)
        self.failed = False

    async def get_batch(self, max_frames: int = 1000) -> list[can.Message]:
        if not self.failed:
            self.failed = True
            raise OSError("driver error escaping the reader")
        return await super().get_batch(max_frames)


async def test_a_failing_ingest_loop_is_restarted_and_reported(db_url: str) -> None:
    """A bus's ingest loop that raises is logged and started again after a backoff (frames
    read afterwards are ingested), and its restart is in the service's status (/readyz,
    /metrics)."""
    src = FailingOnceSource(BUS)
    svc = IngestService(_settings(db_url), sources=[src], retention=False)
    await svc.start()
    try:
        await _until(lambda: src.failed, "the first read")
        await _feed(svc, src, _msgs(1000.0, "voltages", {"v12": 12.5, "v24": 25.0,
                                                         "i12": 1.0, "i24": 2.0}))  # fmt: skip
        (task,) = [t for t in svc.status()["tasks"] if t["name"] == f"ingest {BUS}"]
        assert task["restarts"] == 1 and task["failures"] == 1
        assert task["state"] == "running" and "driver error" in task["last_error"]
        assert svc.live.snapshot("B")[0]["latest"]["voltages"]["fields"]["v12"] == 12.5
    finally:
        assert await svc.stop() == 0
