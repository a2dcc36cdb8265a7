"""API benchmark: read latency under live ingest, and frame-to-websocket latency.

Usage: python -m bench.api [--vehicles 200] [--clients 50] [--ws-clients 100] [--seconds 30]
                          [--seeded 4] [--history-cache-buckets N]
                          [--rates 0 2]

Seeds 24 h of one-second measurements for a few vehicles straight through the store's batched
write path (rollups included, as the ingest makes them), starts `eqgw simulate --vehicles N`
in its own process (its buses served over socketcand, as real buses are read; with
`--in-process-sim` an in-process SimulatedFleet on virtual buses instead) and the gateway with
uvicorn in a child process. From this process, `--clients` clients (bench/http_client.py, a
lean keep-alive client) read `GET /api/v1/vehicles`, `GET /api/v1/vehicles/{id}/live` and a
24 h history at 1 min buckets, closed loop and at each open-loop rate of `--rates`; then
`--ws-clients` websocket clients (each subscribed to one vehicle, as a dashboard page is)
measure the time from a frame's bus timestamp to its `live` event arriving. The simulator
stamps a frame with its scheduled time and puts it on the bus at its next tick (20 ms), so the
websocket figure is an upper bound by up to one tick. Prints p50/p99 and whether each goal is met.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import multiprocessing as mp
import socket
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import httpx
import orjson
import websockets

from bench.http_client import LeanClient
from eqgw.security.keys import create_key
from eqgw.store.engine import create_engine
from eqgw.store.migrate import upgrade_engine
from eqgw.store.writes import Batch, load_unit_ids, write_batch
from eqgw.web.settings import ApiSettings

GOALS_MS = {"live": 25.0, "history_24h_1m": 100.0, "ws": 50.0}
SEEDED = 4  # vehicles with 24 h of history by default (the history requests rotate over them)
DAY_S = 86400
# The gateway's eqgw_api_request_seconds routes of the three reads.
# (route templates as the OpenAPI document names them; tested in tests/test_api_service.py)
SERVER_ROUTES = {
    "/vehicles": "/api/v1/vehicles",
    "/live": "/api/v1/vehicles/{vehicle_id}/live",
    "history": "/api/v1/vehicles/{vehicle_id}/history",
}


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port: int = s.getsockname()[1]
        return port


def seed(url: str, vehicles: list[str], now: float, chunk: int = 20_000) -> int:
    """24 h of 1 s measurements per vehicle through the store's write path; returns rows."""
    engine = create_engine(url)
    upgrade_engine(engine)
    rows = 0
    try:
        for vid in vehicles:
            key = (f"{vid}/sim", 30)
            start = now - DAY_S
            for lo in range(0, DAY_S, chunk):
                batch = Batch()
                batch.vehicles[vid] = {"id": vid, "name": vid, "depot": "simulated"}
                batch.units[key] = vid
                for i in range(lo, min(lo + chunk, DAY_S)):
                    wobble = (i % 600) / 6000.0
                    batch.measurements.append(
                        (
                            key,
                            {
                                "ts": start + i,
                                "v12": 13.1 + wobble,
                                "v24": 26.3 + wobble,
                                "i12": 4.0,
                                "i24": 2.0,
                            },
                        )
                    )
                with engine.begin() as conn:
                    write_batch(conn, batch, load_unit_ids(conn))
                rows += len(batch.measurements)
    finally:
        engine.dispose()
    return rows


def _serve(url: str, port: int, vehicles: int, sim_port: int | None, history_cache: int) -> None:
    """The child process: the gateway and uvicorn; its buses are the simulator's over
    socketcand (`sim_port`), or an in-process SimulatedFleet on virtual buses (None)."""
    import logging

    import uvicorn

    from eqgw.bus.config import BusConfig
    from eqgw.config import Settings, VehicleConfig
    from eqgw.main import create_app
    from eqgw.sim.clock import RealtimeClock
    from eqgw.sim.fleet import SimulatedFleet

    logging.basicConfig(level=logging.WARNING)
    api = ApiSettings(
        port=port, write_rate=1_000_000, ws_queue=20_000, history_cache_buckets=history_cache
    )
    names = [f"SIM-{i:03d}" for i in range(1, vehicles + 1)]
    if sim_port is None:
        sim = SimulatedFleet(vehicles, seed=1, clock=RealtimeClock())
        app = create_app(Settings(database_url=url), api=api, sim=sim)
    else:
        settings = Settings(
            database_url=url,
            vehicles=[VehicleConfig(id=n, name=n, depot="simulated") for n in names],
            buses=[
                BusConfig(
                    name=f"{n}/sim",  # as the seeded history names it
                    vehicle_id=n,
                    interface="socketcand",
                    channel=n,
                    options={"host": "127.0.0.1", "port": sim_port},
                    equalizer_sas=[30, 31],
                )
                for n in names
            ],
        )
        app = create_app(settings, api=api)
    uvicorn.run(app, host="127.0.0.1", port=port, log_level="warning", ws="websockets-sansio")


def _pct(values: list[float], q: float) -> float:
    if not values:
        return float("nan")
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, round(q * (len(ordered) - 1)))]


async def _wait_online(base: str, auth: dict[str, str], vehicles: int, timeout: float) -> int:
    """Wait until (nearly) every simulated vehicle is online; returns how many are."""
    deadline = time.monotonic() + timeout
    online = 0
    async with httpx.AsyncClient(base_url=base, headers=auth, timeout=30) as c:
        while time.monotonic() < deadline:
            try:
                r = await c.get("/api/v1/vehicles")
                if r.status_code == 200:
                    online = sum(v["online"] for v in r.json()["vehicles"])
                    if online >= vehicles:
                        return online
            except httpx.TransportError:
                pass
            await asyncio.sleep(0.5)
    return online


async def http_load(
    base: str,
    auth: dict[str, str],
    names: list[str],
    clients: int,
    seconds: float,
    rate: float = 0.0,
    seeded_n: int = SEEDED,
) -> dict[str, list[float]]:
    """`clients` concurrent clients, each cycling through the three reads; latencies in ms.

    `rate` 0: closed loop, each client sends its next request as soon as the last returns (the
    latency is then the server's queue: clients / throughput). `rate` > 0: open loop, each
    client sends `rate` requests a second on a fixed schedule, and a request's latency counts
    from when it was due, so a server that falls behind is charged for the wait (no
    coordinated omission).
    """
    seeded = names[:seeded_n]
    lat: dict[str, list[float]] = {"vehicles": [], "live": [], "history_24h_1m": []}
    errors: list[str] = []
    stop = time.monotonic() + seconds
    host, port = base.removeprefix("http://").rsplit(":", 1)

    async def client(i: int) -> None:
        c = LeanClient(host, int(port), auth)
        k = i
        due = time.perf_counter() + (i / clients / rate if rate > 0 else 0.0)
        while time.monotonic() < stop:
            k += 1
            if rate > 0:
                await asyncio.sleep(max(0.0, due - time.perf_counter()))
            which = ("vehicles", "live", "history_24h_1m")[k % 3]
            if which == "vehicles":
                path = "/api/v1/vehicles"
            elif which == "live":
                path = f"/api/v1/vehicles/{names[k % len(names)]}/live"
            else:
                # The last 24 h as of now, as a dashboard asks for it: each range is new.
                now = time.time()
                hist = f"from={now - DAY_S:.3f}&to={now:.3f}&bucket=1m&fields=v12,v24"
                path = f"/api/v1/vehicles/{seeded[k % len(seeded)]}/history?{hist}"
            t0 = due if rate > 0 else time.perf_counter()
            due += 1.0 / rate if rate > 0 else 0.0
            status, _size = await c.get(path)
            lat[which].append((time.perf_counter() - t0) * 1000)
            if status != 200:
                errors.append(f"{path}: {status}")
        await c.close()

    await asyncio.gather(*(client(i) for i in range(clients)))
    if errors:
        print(f"  {len(errors)} non-200 answers, e.g. {errors[:3]}")
    return lat


async def ws_latency(
    port: int, key: str, names: list[str], clients: int, seconds: float
) -> tuple[list[float], int]:
    """`clients` websockets, one vehicle each; ms from a frame's bus time to its live event."""
    lat: list[float] = []
    connected = 0
    measuring = asyncio.Event()
    measuring_until = [float("inf")]

    async def client(i: int) -> None:
        nonlocal connected
        url = f"ws://127.0.0.1:{port}/api/v1/ws?key={key}&vehicles={names[i % len(names)]}"
        async with websockets.connect(url, max_size=None, open_timeout=60) as ws:
            connected += 1
            stop = time.monotonic() + 120 + seconds
            # Read from the start (a client that stops reading builds a backlog it then
            # measures); count only once every client is connected and past its snapshot.
            while (left := stop - time.monotonic()) > 0:
                try:
                    raw = await asyncio.wait_for(ws.recv(), timeout=left)
                except TimeoutError:
                    break
                now = time.time()
                if measuring.is_set() and now > measuring_until[0]:
                    break
                msg = orjson.loads(raw)
                if measuring.is_set() and msg.get("type") == "live":
                    lat.append((now - msg["ts"]) * 1000)

    tasks = [asyncio.create_task(client(i)) for i in range(clients)]
    deadline = time.monotonic() + 60
    while connected < clients and time.monotonic() < deadline:
        await asyncio.sleep(0.1)
        if any(t.done() for t in tasks):
            break
    await asyncio.sleep(2.0)  # past the snapshots and the backlog of connecting
    measuring_until[0] = time.time() + seconds
    measuring.set()
    results = await asyncio.gather(*tasks, return_exceptions=True)
    failed = [r for r in results if isinstance(r, BaseException)]
    if failed:
        print(f"  {len(failed)} websocket clients failed, e.g. {failed[0]!r}")
    return lat, connected


async def _scrape(base: str, auth: dict[str, str]) -> dict[str, dict[Any, float]]:
    """From the gateway's /metrics: the event-loop lag histogram (cumulative counts by upper
    bound, in s) under "lag", and the history cache's reads by outcome under "cache"."""
    from prometheus_client.parser import text_string_to_metric_families

    async with httpx.AsyncClient(base_url=base, headers=auth, timeout=30) as c:
        text = (await c.get("/metrics")).text
    out: dict[str, dict[Any, float]] = {"lag": {}, "cache": {}}
    for route in SERVER_ROUTES.values():
        out[route] = {}
    for fam in text_string_to_metric_families(text):
        if fam.name == "eqgw_api_request_seconds":
            for sample in fam.samples:
                route = sample.labels.get("route", "")
                if sample.name.endswith("_bucket") and route in out:
                    le = float(sample.labels["le"])
                    out[route][le] = out[route].get(le, 0.0) + sample.value
        elif fam.name == "eqgw_event_loop_lag_seconds":
            for sample in fam.samples:
                if sample.name.endswith("_bucket"):
                    out["lag"][float(sample.labels["le"])] = sample.value
        elif fam.name == "eqgw_history_cache_reads":
            for sample in fam.samples:
                out["cache"][sample.labels["outcome"]] = sample.value
    return out


def _cache_row(before: dict[str, float], after: dict[str, float]) -> str:
    d = {k: after.get(k, 0.0) - before.get(k, 0.0) for k in ("hit", "miss", "stale")}
    return (
        f"  history cache      {d['hit']:.0f} hits, {d['miss']:.0f} misses, "
        f"{d['stale']:.0f} spans found changed or too old"
    )


def _hist_bounds(
    before: dict[float, float], after: dict[float, float]
) -> tuple[float, Callable[[float], str], list[tuple[float, float]]]:
    """Of the observations between two scrapes of a histogram: how many, a function giving
    the bucket bound a quantile falls under, and the (bound, cumulative count) pairs."""
    bounds = sorted(after)
    pairs = [(b, after[b] - before.get(b, 0.0)) for b in bounds]
    total = pairs[-1][1] if pairs else 0.0

    def bound(q: float) -> str:
        for b, n in pairs:
            if n >= q * total:
                return f"<= {b * 1000:g} ms" if b != float("inf") else "> 2.5 s"
        return "?"

    return total, bound, pairs


def _lag_row(before: dict[float, float], after: dict[float, float]) -> str:
    """p50/p99 of the loop lag probes taken between two scrapes, as histogram bounds."""
    total, bound, pairs = _hist_bounds(before, after)
    if not total:
        return "  event loop lag     no probes"
    late = total - next((n for b, n in pairs if b >= 0.025), 0.0)
    return (
        f"  event loop lag     n={total:>6.0f}  p50 {bound(0.5)}, p99 {bound(0.99)}; "
        f"{late / total:.1%} of probes more than 25 ms late"
    )


def _server_row(before: dict[str, dict[Any, float]], after: dict[str, dict[Any, float]]) -> str:
    """The gateway's own timing of each route (request in to response out), p50/p99 as
    histogram bounds: what the clients measure beyond it is queueing, sockets and the
    client's own process."""
    parts = []
    for name, route in SERVER_ROUTES.items():
        total, bound, _ = _hist_bounds(before[route], after[route])
        parts.append(f"{name} p50 {bound(0.5)}, p99 {bound(0.99)}" if total else f"{name} -")
    return "  server-side        " + "; ".join(parts)


def _row(name: str, values: list[float], goal: float | None) -> str:
    p50, p99 = _pct(values, 0.5), _pct(values, 0.99)
    verdict = "" if goal is None else ("  goal met" if p99 < goal else "  GOAL MISSED")
    goal_s = f" (goal p99 < {goal:.0f} ms)" if goal is not None else ""
    return f"  {name:<18} n={len(values):>6}  p50 {p50:7.1f} ms  p99 {p99:7.1f} ms{goal_s}{verdict}"


async def run(args: argparse.Namespace, url: str) -> None:
    names = [f"SIM-{i:03d}" for i in range(1, args.vehicles + 1)]
    t0 = time.monotonic()
    rows = seed(url, names[: args.seeded], time.time())
    print(f"seeded {rows} measurements (24 h at 1 s, {args.seeded} vehicles) in "
          f"{time.monotonic() - t0:.1f} s")  # fmt: skip
    engine = create_engine(url)
    try:
        _, key = create_key(engine, "bench", "admin")
    finally:
        engine.dispose()
    auth = {"Authorization": f"Bearer {key}"}
    port = _free_port()
    base = f"http://127.0.0.1:{port}"
    sim = None
    sim_port: int | None = None
    if not args.in_process_sim:
        from tests.cluster_helpers import start_simulator

        sim, sim_port = start_simulator(Path(url.split("///", 1)[1]).parent, args.vehicles)
        print(f"simulator: eqgw simulate --vehicles {args.vehicles} in its own process, "
              f"served over socketcand on port {sim_port}")  # fmt: skip
    else:
        print(f"simulator: in the gateway's process ({args.vehicles} vehicles, virtual buses)")
    proc = mp.get_context("spawn").Process(
        target=_serve,
        args=(url, port, args.vehicles, sim_port, args.history_cache_buckets),
        daemon=True,
    )
    proc.start()
    try:
        online = await _wait_online(base, auth, args.vehicles, timeout=120)
        print(f"server up with {args.vehicles} simulated vehicles ingesting in real time; "
              f"{online} online")  # fmt: skip
        async with httpx.AsyncClient(base_url=base, headers=auth) as c:
            status = (await c.get("/readyz")).json()
        open_buses = sum(b["state"] == "open" for b in status["buses"])
        print(f"{open_buses} of {len(status['buses'])} buses open")
        for rate in args.rates:
            m0 = await _scrape(base, auth)
            lat = await http_load(base, auth, names, args.clients, args.seconds, rate, args.seeded)
            m1 = await _scrape(base, auth)
            n = sum(len(v) for v in lat.values())
            mode = f"open loop, {rate:g} requests/s each" if rate > 0 else "closed loop (no pause)"
            print(f"HTTP, {args.clients} concurrent clients, {mode}, {args.seconds:.0f} s, "
                  f"during ingest: {n / args.seconds:,.0f} requests/s served")  # fmt: skip
            print(_row("GET /vehicles", lat["vehicles"], GOALS_MS["live"]))
            print(_row("GET /{id}/live", lat["live"], GOALS_MS["live"]))
            print(_row("24 h history, 1m", lat["history_24h_1m"], GOALS_MS["history_24h_1m"]))
            print(_server_row(m0, m1))
            print(_lag_row(m0["lag"], m1["lag"]))
            print(_cache_row(m0["cache"], m1["cache"]))
        m0 = await _scrape(base, auth)
        ws, connected = await ws_latency(port, key, names, args.ws_clients, args.ws_seconds)
        m1 = await _scrape(base, auth)
        print(f"websocket, {connected} clients connected (one vehicle each), "
              f"{args.ws_seconds:.0f} s:")  # fmt: skip
        print(_row("frame -> websocket", ws, GOALS_MS["ws"]))
        print(_lag_row(m0["lag"], m1["lag"]))
    finally:
        proc.terminate()
        proc.join(timeout=30)
        if proc.is_alive():
            proc.kill()
        if sim is not None:
            sim.stop()


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0] if __doc__ else None)
    p.add_argument("--vehicles", type=int, default=200)
    p.add_argument("--clients", type=int, default=50)
    p.add_argument("--ws-clients", type=int, default=100)
    p.add_argument("--seconds", type=float, default=30.0, help="length of each HTTP phase")
    p.add_argument(
        "--in-process-sim",
        action="store_true",
        help="run the simulated fleet inside the gateway's process (default: `eqgw simulate` "
        "in its own process, its buses read over socketcand, as real buses would be)",
    )
    p.add_argument(
        "--rates",
        type=float,
        nargs="+",
        default=[0.0, 2.0],
        help="HTTP phases: requests/s per client (0 = closed loop, as fast as answered)",
    )
    p.add_argument("--ws-seconds", type=float, default=20.0, help="length of the websocket phase")
    p.add_argument(
        "--seeded",
        type=int,
        default=SEEDED,
        help="vehicles with 24 h of history, which the history requests rotate over",
    )
    p.add_argument(
        "--history-cache-buckets",
        type=int,
        default=ApiSettings().history_cache_buckets,
        help="the gateway's EQGW_API_HISTORY_CACHE_BUCKETS (0: every history read from the "
        "database, the comparison without the cache)",
    )
    args = p.parse_args()
    with tempfile.TemporaryDirectory(prefix="eqgw-bench-api-") as tmp:
        url = f"sqlite:///{Path(tmp) / 'eqgw.db'}"
        print(f"python {sys.version.split()[0]}, database {url}")
        with contextlib.suppress(KeyboardInterrupt):
            asyncio.run(run(args, url))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
