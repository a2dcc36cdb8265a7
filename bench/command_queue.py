"""Command queue benchmark: what queueing a command costs now that the database serializes it
(the Idempotency-Key lookup, the conflict check against the bus's pending rows and the insert,
in one transaction holding the bus's lock), alone and with threads racing.

Usage: python -m bench.command_queue [--url URL] [--commands 200] [--threads 4]

On a fresh SQLite file (BEGIN IMMEDIATE), or on URL (a PostgreSQL database the bench may write
to: advisory transaction locks), it times `CommandService._queue`, the transaction every
gateway's submit runs, for `--commands` parameter writes each with an Idempotency-Key:
- one thread, one bus (the latency a request adds);
- `--threads` threads on one bus (they queue through its lock);
- `--threads` threads on a bus each (PostgreSQL: no shared lock; SQLite: one write lock).
Each write is a different parameter, so none conflicts; the pending rows grow as a busy bus's
would. Prints median and p90 per commit in ms and commits/s.
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import threading
import time
import uuid
from pathlib import Path
from typing import Any

from sqlalchemy import Engine, text

from eqgw.commands.model import Command
from eqgw.commands.service import CommandService
from eqgw.ingest.state import LiveState
from eqgw.store.engine import create_engine
from eqgw.store.migrate import upgrade_engine
from eqgw.web.settings import ApiSettings


def _row(bus: str, i: int) -> dict[str, Any]:
    now = time.time()
    name = f"p{i}"  # a parameter of its own: the conflict check reads every row, finds none
    return {
        "id": str(uuid.uuid4()),
        "kind": "parameters",
        "vehicle_id": bus.split("/")[0],
        "bus": bus,
        "sa": 30,
        "payload": {"request": {name: 1}, "values": {name: 1}, "affected_units": [{"sa": 30}]},
        "state": "queued",
        "reason": None,
        "created_at": now,
        "updated_at": now,
        "expires_at": now + 300,
        "first_sent_at": None,
        "last_sent_at": None,
        "sends": 0,
        "max_sends": 3,
        "key_id": 1,
        "key_name": "bench",
        "idempotency_key": f"bench-{uuid.uuid4().hex}",
    }


def _run(svc: CommandService, buses: list[str], per_thread: int) -> tuple[list[float], float]:
    engine = svc._serial_engine
    times: list[float] = []
    lock = threading.Lock()
    start = threading.Barrier(len(buses))

    def work(bus: str, offset: int) -> None:
        mine = []
        start.wait()
        for i in range(per_thread):
            row = _row(bus, offset + i)
            cmd = Command.from_row(row)
            t0 = time.perf_counter()
            with engine.begin() as conn:
                svc._queue(conn, cmd, row["payload"]["request"])
            mine.append((time.perf_counter() - t0) * 1000)
        with lock:
            times.extend(mine)

    threads = [
        threading.Thread(target=work, args=(bus, n * per_thread)) for n, bus in enumerate(buses)
    ]
    t0 = time.perf_counter()
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    return times, time.perf_counter() - t0


def _clear(engine: Engine) -> None:
    with engine.begin() as conn:
        conn.execute(text("DELETE FROM commands"))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--url", help="PostgreSQL URL (default: a fresh SQLite file)")
    ap.add_argument("--commands", type=int, default=200)
    ap.add_argument("--threads", type=int, default=4)
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        url = args.url or f"sqlite:///{Path(tmp) / 'bench.db'}"
        engine = create_engine(url, pool_size=args.threads + 2)
        upgrade_engine(engine)
        svc = CommandService(engine, LiveState(), {}, {}, set, ApiSettings())
        print(f"{engine.dialect.name}: {args.commands} commands per case")
        per = max(1, args.commands // args.threads)
        cases = [
            ("1 thread, 1 bus", ["V1/can0"], args.commands),
            (f"{args.threads} threads, 1 bus", ["V1/can0"] * args.threads, per),
            (
                f"{args.threads} threads, {args.threads} buses",
                [f"V{n}/can0" for n in range(args.threads)],
                per,
            ),
        ]
        for name, buses, n in cases:
            _clear(engine)
            ms, wall = _run(svc, buses, n)
            p90 = sorted(ms)[int(0.9 * (len(ms) - 1))]
            print(
                f"  {name:<24} median {statistics.median(ms):6.2f} ms  p90 {p90:6.2f} ms  "
                f"{len(ms) / wall:7.0f} commits/s"
            )
        engine.dispose()


if __name__ == "__main__":
    main()
