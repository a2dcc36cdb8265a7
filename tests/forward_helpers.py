"""Shared pieces of the edge-forwarding tests: a central `eqgw serve` in a subprocess, a
simulated vehicle whose sent frames are recorded, and the history compared with a replay."""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import can
import httpx
from sqlalchemy import Engine, func, select

from eqgw.bus.config import BusConfig
from eqgw.config import Settings, VehicleConfig
from eqgw.forward.protocol import flags_of, is_equalizer_frame
from eqgw.ingest.replay import replay_file
from eqgw.security.keys import create_key
from eqgw.sim.clock import ManualClock
from eqgw.sim.fleet import SimulatedFleet
from eqgw.store.archive import count_frames
from eqgw.store.engine import create_engine
from eqgw.store.forward_models import ForwardStream
from eqgw.store.migrate import upgrade_engine
from eqgw.store.models import RAW_TABLES, all_metadata
from tests.api_helpers import wait_for
from tests.proc_helpers import Process, eqgw, wait_until
from tests.support import web

ROOT = Path(__file__).resolve().parents[1]
VEHICLE = "SIM-001"
# Tables whose rows come from frames (live_state follows wall time and restarts: left out);
# the raw archive counted in frames (`raw_frames`), whether packed or not yet.
_ARCHIVE = ("raw_blocks", "raw_recent")
HISTORY_TABLES = (
    "units",
    *(t.name for t in RAW_TABLES if t.name not in _ARCHIVE),
    "raw_frames",
    "fault_episodes",
    "rollups",
)


def central_config(tmp_path: Path, db_url: str) -> tuple[Path, str]:
    """A central fleet file naming the forwarded vehicle; the database migrated, and an
    ingest key made (returned)."""
    path = tmp_path / "central.toml"
    # Alerting is off: these tests are about frames, and its rules add nothing here. The
    # simulated vehicles' clocks run minutes ahead of the wall clock (time passes in steps):
    # frames up to an hour ahead are taken.
    path.write_text(
        f'database_url = "{db_url}"\n\n[alerts]\nenabled = false\n\n'
        "[forward]\nmax_future_s = 3600\n\n"
        f'[[vehicles]]\nid = "{VEHICLE}"\n'
    )
    engine = create_engine(db_url)
    try:
        upgrade_engine(engine)
        create_key(engine, "admin", "admin")  # so the first start prints no key of its own
        _, key = create_key(engine, VEHICLE, "ingest")
    finally:
        engine.dispose()
    return path, key


@contextmanager
def central(tmp_path: Path, config: Path, port: int) -> Iterator[Process]:
    """`eqgw serve --config ... --port ...`, ready (answering /healthz), stopped at the end."""
    p = start_central(tmp_path, config, port)
    try:
        yield p
    finally:
        p.stop()


def start_central(tmp_path: Path, config: Path, port: int) -> Process:
    p = Process(eqgw("serve", "--config", str(config), "--port", str(port)), tmp_path)

    def up() -> bool:
        if p.proc.poll() is not None:
            raise AssertionError("eqgw serve exited:\n" + p.output())
        try:
            return web.get(f"http://127.0.0.1:{port}/healthz", timeout=2).status_code == 200
        except httpx.TransportError:
            return False

    wait_until(up, 90, "eqgw serve to answer")
    return p


class RecordedVehicle:
    """A simulated vehicle (forwarded as SIM-001 whatever its simulator name) on a manual
    clock (wall-clock epoch, so retention keeps its rows), with every frame it sends recorded."""

    def __init__(self, seed: int = 2, pick: int = 1) -> None:
        # The fleet mixes series and unit counts by position: vehicle 3 has two 80-series units.
        self.fleet = SimulatedFleet(pick, seed=seed, clock=ManualClock(time.time()))
        self.name = f"SIM-{pick:03d}"
        self.vehicle = self.fleet.vehicle(self.name)
        self.sas = [u.sa for u in self.vehicle.spec.units]
        self.sent: list[can.Message] = []
        self.vehicle.taps.append(self.sent.append)

    @property
    def channel(self) -> str:
        return self.fleet.channels[self.name]

    def kept(self) -> list[can.Message]:
        """The frames a forwarder keeps by default (the equalizer frames)."""
        sas = frozenset(self.sas)
        return [m for m in self.sent if is_equalizer_frame(m.arbitration_id, flags_of(m), sas)]


def table_counts(db_url: str) -> dict[str, int]:
    tables = all_metadata().tables
    engine = create_engine(db_url)
    try:
        with engine.connect() as conn:
            return {
                t: (
                    count_frames(conn)
                    if t == "raw_frames"
                    else int(conn.execute(select(func.count()).select_from(tables[t])).scalar_one())
                )
                for t in HISTORY_TABLES
            }
    finally:
        engine.dispose()


def replay_counts(messages: list[can.Message], tmp_path: Path, sas: list[int]) -> dict[str, int]:
    """The same frames replayed into a fresh SQLite file: what the history must hold."""
    url = f"sqlite:///{tmp_path / 'replay.db'}"
    for m in messages:
        m.channel = "can0"
    # A configured bus lends the replay the equalizer addresses the forwarder sends.
    settings = Settings(
        database_url=url,
        vehicles=[VehicleConfig(id=VEHICLE)],
        buses=[
            BusConfig(
                name=VEHICLE, vehicle_id=VEHICLE, interface="virtual", channel="can0",
                equalizer_sas=sas,
            )
        ],
    )  # fmt: skip
    replay_file(tmp_path / "none.log", {"can0": VEHICLE}, settings, messages=messages)
    return table_counts(url)


def stream_row(engine: Engine) -> dict[str, Any] | None:
    """The central's only forwarder stream row (None before the first commit)."""
    with engine.connect() as conn:
        row = conn.execute(select(ForwardStream.__table__)).first()
        return row._asdict() if row is not None else None


async def async_wait(cond: Callable[[], Any], timeout: float = 60.0, what: str = "it") -> Any:
    """`wait_for` with a plain condition, for tests whose event loop runs a forwarder (never
    block the loop)."""

    async def check() -> Any:
        return cond()

    return await wait_for(check, timeout, what)
