"""Edge-forwarding benchmark: frames/s one central `eqgw serve` absorbs from N concurrent
forwarders, beside the central's replay rate of the same frames (the baseline, same run).

Usage: python -m bench.forward [--forwarders 1 4 16] [--minutes 60] [--db sqlite|postgres]

Four simulated vehicles (70- and 80-series, single and parallel units) drive for `--minutes`
on a manual clock; their equalizer frames are what a forwarder keeps. Forwarder i uploads vehicle
i mod 4's frames as vehicle FWD-i (its own units and rows). For each N: a fresh database, a
fresh `eqgw serve` subprocess (alerting off, as the replay has none), N forwarders' buffers
filled beforehand, then N `Uploader`s in this process (gzip JSON, 2000 frames per upload) empty
them concurrently; the rate is frames / time until the last acknowledgement. The baseline is
`eqgw replay`'s path (`replay_file`) of the same N streams, merged in time order, into another
fresh database of the same engine.
"""

from __future__ import annotations

import argparse
import asyncio
import os
import tempfile
import time
import uuid
from pathlib import Path

import can
from sqlalchemy import text

from eqgw.bus.config import BusConfig
from eqgw.config import Settings, VehicleConfig
from eqgw.forward.buffer import FrameBuffer
from eqgw.forward.protocol import flags_of, is_equalizer_frame
from eqgw.forward.uploader import Uploader, UploadSettings
from eqgw.ingest.replay import replay_file
from eqgw.security.keys import create_key
from eqgw.sim.clock import ManualClock
from eqgw.sim.fleet import SimulatedFleet
from eqgw.store.engine import create_engine
from eqgw.store.migrate import upgrade_engine
from tests.proc_helpers import Process, eqgw, free_port, wait_until

PG_DEFAULT = os.environ.get("EQGW_BENCH_PG", "postgresql+psycopg://postgres@127.0.0.1:5432/test")
SIM_VEHICLES = 4

Frame = tuple[float, int, bytes, int]


def simulate(minutes: float) -> list[tuple[list[Frame], tuple[int, ...]]]:
    """Equalizer frames of SIM_VEHICLES simulated vehicles over `minutes`."""
    fleet = SimulatedFleet(SIM_VEHICLES, seed=0, clock=ManualClock(time.time() - minutes * 60))
    sent: dict[str, list[can.Message]] = {name: [] for name in fleet.vehicles}
    for name, v in fleet.vehicles.items():
        v.taps.append(sent[name].append)
    with fleet:
        for _ in range(int(minutes * 6)):
            fleet.advance(10.0)
    out = []
    for name, msgs in sent.items():
        sas = frozenset(u.sa for u in fleet.vehicle(name).spec.units)
        frames = [
            (m.timestamp, m.arbitration_id, bytes(m.data), flags_of(m))
            for m in msgs
            if is_equalizer_frame(m.arbitration_id, flags_of(m), sas)
        ]
        out.append((frames, tuple(sorted(sas))))
    return out


class Database:
    """A fresh database per measurement: a SQLite file or a PostgreSQL schema."""

    def __init__(self, kind: str, workdir: Path, pg: str) -> None:
        self.kind, self.workdir, self.pg = kind, workdir, pg
        self._schemas: list[str] = []

    def new(self, tag: str) -> str:
        if self.kind == "sqlite":
            return f"sqlite:///{self.workdir / f'{tag}.db'}"
        schema = f"bench_fwd_{uuid.uuid4().hex[:10]}"
        admin = create_engine(self.pg)
        with admin.begin() as conn:
            conn.execute(text(f'CREATE SCHEMA "{schema}"'))
        admin.dispose()
        self._schemas.append(schema)
        return f"{self.pg}?options=-csearch_path%3D{schema}"

    def drop_all(self) -> None:
        if not self._schemas:
            return
        admin = create_engine(self.pg)
        with admin.begin() as conn:
            for s in self._schemas:
                conn.execute(text(f'DROP SCHEMA "{s}" CASCADE'))
        admin.dispose()


def vehicle_ids(n: int) -> list[str]:
    return [f"FWD-{i:02d}" for i in range(1, n + 1)]


def replay_rate(
    streams: list[list[Frame]], sas: list[tuple[int, ...]], ids: list[str], url: str
) -> float:
    merged = []
    for vid, frames in zip(ids, streams, strict=True):
        for ts, can_id, data, flags in frames:
            merged.append(
                can.Message(
                    timestamp=ts,
                    arbitration_id=can_id,
                    data=data,
                    is_extended_id=bool(flags & 1),
                    channel=vid,
                    check=False,
                )
            )
    merged.sort(key=lambda m: m.timestamp)
    # Configured buses lend the replay each vehicle's equalizer addresses, as the uploads carry.
    settings = Settings(
        database_url=url,
        vehicles=[VehicleConfig(id=v) for v in ids],
        buses=[
            BusConfig(name=v, vehicle_id=v, interface="virtual", channel=v, equalizer_sas=list(a))
            for v, a in zip(ids, sas, strict=True)
        ],
    )
    summary = replay_file(Path("bench"), {v: v for v in ids}, settings, messages=merged)
    return summary.frames / summary.seconds


async def upload_rate(
    streams: list[list[Frame]],
    sas: list[tuple[int, ...]],
    ids: list[str],
    url: str,
    workdir: Path,
    tag: str,
) -> tuple[float, float]:
    """(frames/s, seconds) of N forwarders emptying their buffers into a fresh central."""
    config = workdir / f"{tag}.toml"
    config.write_text(
        f'database_url = "{url}"\n\n[alerts]\nenabled = false\n\n'
        + "".join(f'[[vehicles]]\nid = "{v}"\n\n' for v in ids)
    )
    engine = create_engine(url)
    upgrade_engine(engine)
    create_key(engine, "admin", "admin")
    _, key = create_key(engine, "bench", "ingest")
    engine.dispose()
    port = free_port()
    central = Process(eqgw("serve", "--config", str(config), "--port", str(port)), workdir)
    try:
        import httpx

        def up() -> bool:
            assert central.proc.poll() is None, central.output()
            try:
                return httpx.get(f"http://127.0.0.1:{port}/healthz", timeout=2).status_code == 200
            except httpx.TransportError:
                return False

        await asyncio.to_thread(wait_until, up, 120, "eqgw serve")
        buffers = []
        uploaders = []
        for vid, frames, unit_sas in zip(ids, streams, sas, strict=True):
            buf = FrameBuffer(workdir / f"{tag}-{vid}.db")
            buf.add(frames)
            buffers.append(buf)
            uploaders.append(
                Uploader(
                    buf,
                    UploadSettings(
                        url=f"http://127.0.0.1:{port}/api/v1",
                        key=key,
                        vehicle=vid,
                        bus=vid,
                        equalizer_sas=unit_sas,
                        backoff_initial_s=0.05,
                        backoff_max_s=0.5,
                        idle_poll_s=0.05,
                        timeout_s=120,
                    ),
                )
            )
        total = sum(len(f) for f in streams)
        started = time.perf_counter()
        tasks = [asyncio.create_task(u.run()) for u in uploaders]
        while any(b.rows for b in buffers):
            await asyncio.sleep(0.02)
        seconds = time.perf_counter() - started
        for t in tasks:
            t.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)
        failures = sum(u.status().failures for u in uploaders)
        if failures:
            print(f"  ({failures} failed uploads retried)")
        for b in buffers:
            b.close()
        return total / seconds, seconds
    finally:
        central.stop()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--forwarders", type=int, nargs="+", default=[1, 4, 16])
    ap.add_argument("--minutes", type=float, default=60.0, help="simulated minutes per vehicle")
    ap.add_argument("--db", choices=("sqlite", "postgres"), default="sqlite")
    ap.add_argument("--pg", default=PG_DEFAULT, help="PostgreSQL URL (a schema per run)")
    args = ap.parse_args()
    base = simulate(args.minutes)
    per = [len(f) for f, _ in base]
    print(
        f"frames: {SIM_VEHICLES} simulated vehicles x {args.minutes:g} min, "
        f"{min(per):,}-{max(per):,} equalizer frames each; forwarder i sends vehicle i mod "
        f"{SIM_VEHICLES}'s; central: eqgw serve on {args.db}, 2000 frames per gzip upload"
    )
    head = f"{'forwarders':>10} {'frames':>9} {'upload -> central':>20} {'replay (baseline)':>20}"
    print(head + "  ratio")
    with tempfile.TemporaryDirectory(prefix="eqgw-bench-fwd-") as tmp:
        workdir = Path(tmp)
        db = Database(args.db, workdir, args.pg)
        try:
            for n in args.forwarders:
                ids = vehicle_ids(n)
                streams = [base[i % SIM_VEHICLES][0] for i in range(n)]
                sas = [base[i % SIM_VEHICLES][1] for i in range(n)]
                url = db.new(f"up{n}")
                up, _ = asyncio.run(upload_rate(streams, sas, ids, url, workdir, f"up{n}"))
                rp = replay_rate(streams, sas, ids, db.new(f"rp{n}"))
                total = sum(len(s) for s in streams)
                print(
                    f"{n:>10} {total:>9,} {up:>13,.0f} frames/s {rp:>13,.0f} frames/s  "
                    f"{up / rp:.2f}"
                )
        finally:
            db.drop_all()


if __name__ == "__main__":
    main()
