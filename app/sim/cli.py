"""`eqgw simulate`: serve a simulated equalizer fleet over socketcand."""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import signal
import sys
from pathlib import Path
from typing import Any

DEFAULT_LISTEN = "127.0.0.1:29536"


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """Add `eqgw simulate` to the command line."""
    p = subparsers.add_parser(
        "simulate",
        help="run a simulated fleet of equalizers, served over socketcand",
        description=(
            "Simulate vehicles with VANN-Guard equalizers (70- and 80-series, some with two "
            "units in parallel) and serve each vehicle's CAN bus over the socketcand protocol "
            "(raw mode) under the vehicle's name."
        ),
    )
    p.add_argument(
        "--vehicles",
        type=int,
        default=None,
        help="number of vehicles (default 20, or the scenario's vehicles)",
    )
    p.add_argument(
        "--listen",
        default=DEFAULT_LISTEN,
        metavar="HOST:PORT",
        help=f"socketcand address (default {DEFAULT_LISTEN}; port 0 picks a free one)",
    )
    p.add_argument("--record", metavar="DIR", help="write each bus to DIR/<name>.log (candump -L)")
    p.add_argument("--speed", type=float, default=1.0, help="simulated seconds per real second")
    p.add_argument(
        "--scenario",
        metavar="FILE",
        help="YAML/TOML scenario file, or the name of a built-in one (see --list-scenarios)",
    )
    p.add_argument("--list-scenarios", action="store_true", help="list built-in scenarios")
    p.add_argument(
        "--seed",
        type=int,
        default=None,
        help="seed for a repeatable fleet (default: the scenario's, else 0)",
    )
    p.add_argument(
        "--background-traffic",
        action="store_true",
        help="add other J1939 nodes (engine EEC1/CCVS/ET1/VEP1, transmission, a foreign device)",
    )
    p.add_argument(
        "--start-on-connect",
        action="store_true",
        help="hold the simulated clock (and the scenario's events) until a client reads every "
        "bus in raw mode, so a gateway started later sees the scenario from its start",
    )
    p.add_argument(
        "--duration",
        type=float,
        default=None,
        metavar="SECONDS",
        help="stop after this many simulated seconds, every vehicle simulated up to exactly "
        "then, however long that takes (default: run until interrupted)",
    )
    p.set_defaults(func=run)


def _say(text: str) -> None:
    sys.stdout.write(text + "\n")
    sys.stdout.flush()


def _parse_listen(value: str) -> tuple[str, int]:
    host, sep, port = value.rpartition(":")
    if not sep or not port.isdigit() or not 0 <= int(port) <= 65535:
        raise ValueError(f"--listen wants HOST:PORT, got {value!r}")
    return host or "127.0.0.1", int(port)


def _resolve_scenario(value: str) -> Path:
    from eqgw.sim.scenario import builtin_scenarios

    path = Path(value)
    if path.exists():
        return path
    builtin = builtin_scenarios()
    if value in builtin:
        return builtin[value]
    raise ValueError(f"no scenario file {value!r}; built-in: {', '.join(builtin) or 'none'}")


def describe_lines(description: list[dict[str, Any]]) -> list[str]:
    """One line per served bus: name, series, source addresses and models."""
    lines = []
    for v in description:
        units = v["units"]
        series = "/".join(sorted({f"{u['series']}-series" for u in units}))
        sas = ",".join(str(u["sa"]) for u in units)
        models = ", ".join(u["model"] for u in units)
        lines.append(f"  {v['name']:<12} {series:<10} SA {sas:<6} {models}")
    return lines


def run(args: argparse.Namespace) -> int:
    """Entry point of `eqgw simulate`."""
    from eqgw.sim.scenario import ScenarioError, builtin_scenarios

    if args.list_scenarios:
        for name, path in builtin_scenarios().items():
            _say(f"{name}\t{path}")
        return 0
    try:
        host, port = _parse_listen(args.listen)
        scenario_path = _resolve_scenario(args.scenario) if args.scenario else None
        if args.speed <= 0:
            raise ValueError("--speed must be positive")
        return asyncio.run(_serve(args, host, port, scenario_path))
    except (ValueError, ScenarioError) as exc:
        sys.stderr.write(f"eqgw simulate: {exc}\n")
        return 2


async def _serve(args: argparse.Namespace, host: str, port: int, scenario: Path | None) -> int:
    from eqgw.bus.socketcand_server import SocketcandServer
    from eqgw.sim.clock import RealtimeClock
    from eqgw.sim.fleet import SimulatedFleet
    from eqgw.sim.scenario import load_scenario

    loaded = load_scenario(scenario) if scenario else None
    count = args.vehicles
    if count is None:
        count = len(loaded.vehicles) if loaded and loaded.vehicles else 20
    fleet = SimulatedFleet(
        count,
        seed=args.seed,
        scenario=loaded,
        clock=RealtimeClock(args.speed),
        background_traffic=args.background_traffic,
        record_dir=args.record,
    )
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        with contextlib.suppress(NotImplementedError, RuntimeError):
            loop.add_signal_handler(sig, stop.set)
    if args.duration is not None:
        fleet.run_for(args.duration)
    server = SocketcandServer(host, port, buses=fleet.channels)
    if not args.start_on_connect:
        await fleet.start()
    try:
        await server.start()
        # The first line is for scripts and tests: the address actually bound.
        _say(f"listening {host}:{server.port}")
        _say(
            f"eqgw simulate: {len(fleet.vehicles)} buses over socketcand on {host}:{server.port}"
            f" (speed {args.speed:g}x, seed {fleet.seed}"
            + (f", scenario {loaded.name}" if loaded else "")
            + (", background traffic" if args.background_traffic else "")
            + (f", recording to {args.record}" if args.record else "")
            + ")"
        )
        for line in describe_lines(fleet.describe()):
            _say(line)
        if args.start_on_connect:
            wanted = set(fleet.channels)
            while not stop.is_set():
                reading = {c.bus for c in server.clients() if c.rawmode}
                if wanted <= reading:
                    break
                with contextlib.suppress(TimeoutError):
                    async with asyncio.timeout(0.1):
                        await stop.wait()
            if not stop.is_set():
                await fleet.start()
                _say("every bus is read: the simulation starts")
        while not stop.is_set():
            if fleet.error is not None:
                raise RuntimeError("the simulation stopped") from fleet.error
            if fleet.finished:
                break
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout(0.1):
                    await stop.wait()
    finally:
        await server.stop()
        await fleet.stop()
    _say("stopped")
    return 0
