"""A simulated fleet: one python-can virtual bus per vehicle, stepped by hand or in real time.

Tests build a fleet on a `ManualClock` and call `advance()`; `eqgw simulate` and the demo run it
on a `RealtimeClock` (optionally faster) with `await start()` or `start_thread()`. Frames carry
simulated time as their timestamps.
"""

from __future__ import annotations

import asyncio
import itertools
import math
import os
import random
import threading
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from types import TracebackType
from typing import Any

import can
from can.io.canutils import CanutilsLogWriter

from eqgw.sim.clock import ManualClock, RealtimeClock, SimClock
from eqgw.sim.equalizer import EqualizerSpec
from eqgw.sim.scenario import Event, Scenario, builtin_scenarios, load_scenario
from eqgw.sim.vehicle import SimulatedVehicle, VehicleSpec
from eqgw.tasks import cancel_and_wait

DEFAULT_TICK_S = 0.02
# A recording (`record_dir`) is flushed to its files at least this often while the fleet runs
# in real time, so a reader of the files (tail -f, a test) sees what was sent within this.
RECORD_FLUSH_S = 0.25
_fleet_ids = itertools.count(1)


def generate_specs(count: int, seed: int, start: int = 1) -> list[VehicleSpec]:
    """`count` vehicles named SIM-001.. with a seeded mix of series, ratings and parallel units.

    The first three are always an 80-series, a 70-series and an 80-series pair (SA 30 and 31),
    so even a small fleet shows each kind.
    """
    specs: list[VehicleSpec] = []
    for i in range(count):
        number = start + i
        rng = random.Random(f"eqgw-sim:{seed}:{number}")
        if number == 1:
            series, rating, pair = 80, 100, False
        elif number == 2:
            series, rating, pair = 70, 80, False
        elif number == 3:
            series, rating, pair = 80, 60, True
        else:
            series = 80 if rng.random() < 0.6 else 70
            rating = rng.choice((60, 80, 100))
            pair = rng.random() < 0.2
        units = [EqualizerSpec(sa=30, series=series, rating_a=rating)]
        if pair:
            units.append(EqualizerSpec(sa=31, series=series, rating_a=rating))
        soc = rng.uniform(0.75, 0.98)
        specs.append(
            VehicleSpec(
                name=f"SIM-{number:03d}",
                units=units,
                battery_ah=rng.choice((100.0, 150.0, 200.0, 225.0)),
                soc_a=soc,
                soc_b=min(1.0, soc + rng.uniform(0.0, 0.02)),
                load_12v_a=round(rng.uniform(5.0, 0.5 * rating * len(units)), 1),
                load_24v_a=round(rng.uniform(2.0, 15.0), 1),
                alternator_on=rng.random() < 0.7,
                temperature_c=round(rng.uniform(5.0, 30.0), 1),
            )
        )
    return specs


class SimulatedFleet:
    """Vehicles with equalizers on python-can virtual buses; inject events; step or run."""

    def __init__(
        self,
        vehicles: int | Sequence[VehicleSpec] | None = None,
        *,
        seed: int | None = None,
        scenario: Scenario | str | Path | None = None,
        clock: SimClock | None = None,
        speed: float = 1.0,
        background_traffic: bool = False,
        record_dir: str | Path | None = None,
        channel_prefix: str | None = None,
        tick_s: float = DEFAULT_TICK_S,
    ) -> None:
        if isinstance(scenario, str | Path):
            builtin = builtin_scenarios()
            if not Path(scenario).exists() and str(scenario) in builtin:
                scenario = builtin[str(scenario)]
            scenario = load_scenario(scenario)
        self.scenario = scenario or Scenario()
        # An explicit seed wins over the scenario's; neither means 0.
        if seed is None:
            seed = self.scenario.seed if self.scenario.seed is not None else 0
        self.seed = seed
        specs: list[VehicleSpec] = list(self.scenario.vehicles)
        if isinstance(vehicles, int):
            if vehicles < 0:
                raise ValueError("vehicle count must not be negative")
            specs += generate_specs(max(0, vehicles - len(specs)), seed)
        elif vehicles is not None:
            specs += list(vehicles)
        elif not specs:
            specs = generate_specs(3, seed)
        names = [s.name for s in specs]
        if len(set(names)) != len(names):
            raise ValueError(f"vehicle names must be unique: {names}")
        for event in self.scenario.events:
            if event.vehicle != "all" and event.vehicle not in names:
                raise ValueError(f"scenario event for unknown vehicle {event.vehicle!r}")
        self.clock: SimClock = clock if clock is not None else RealtimeClock(speed)
        prefix = channel_prefix or f"eqgw-sim-{os.getpid()}-{next(_fleet_ids)}"
        self.vehicles: dict[str, SimulatedVehicle] = {}
        for spec in specs:
            rng = random.Random(f"eqgw-sim-run:{seed}:{spec.name}")
            self.vehicles[spec.name] = SimulatedVehicle(
                spec, f"{prefix}/{spec.name}", rng=rng, background_traffic=background_traffic
            )
        self.record_dir = Path(record_dir) if record_dir is not None else None
        self.tick_s = tick_s
        self._writers: list[CanutilsLogWriter] = []
        self._flushed_at = 0.0  # time.monotonic() of the recording's last flush
        self._pending: dict[str, list[Event]] = {name: [] for name in self.vehicles}
        for event in self.scenario.events:
            targets = list(self.vehicles) if event.vehicle == "all" else [event.vehicle]
            for name in targets:
                self._pending[name].append(event)
        self._lock = threading.RLock()
        self._opened = False
        self.t0: float | None = None
        self._task: asyncio.Task[None] | None = None
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self.error: BaseException | None = None
        # Simulated seconds after the start where the run ends (`run_for`); None: no end.
        self.duration: float | None = None
        self._finished = False

    # ----- lookup -----------------------------------------------------------------------------
    @property
    def names(self) -> list[str]:
        return list(self.vehicles)

    @property
    def channels(self) -> dict[str, str]:
        """Vehicle name -> python-can virtual channel name (what socketcand serves)."""
        return {name: v.channel for name, v in self.vehicles.items()}

    def vehicle(self, name: str) -> SimulatedVehicle:
        try:
            return self.vehicles[name]
        except KeyError:
            raise KeyError(f"no vehicle {name!r} in the fleet; have {self.names}") from None

    def describe(self) -> list[dict[str, Any]]:
        """Per vehicle: name, channel and units (SA, series, model)."""
        return [{**v.spec.describe(), "channel": v.channel} for v in self.vehicles.values()]

    def now(self) -> float:
        return self.clock.now()

    @property
    def elapsed(self) -> float:
        """Simulated seconds since the fleet started."""
        return 0.0 if self.t0 is None else self.clock.now() - self.t0

    # ----- lifecycle --------------------------------------------------------------------------
    def open(self) -> None:
        """Open every vehicle's bus (and log file) and power the units up at the clock's now."""
        with self._lock:
            if self._opened:
                return
            if self.record_dir is not None:
                self.record_dir.mkdir(parents=True, exist_ok=True)
            try:
                for vehicle in self.vehicles.values():
                    vehicle.open()
                    if self.record_dir is not None:
                        writer = CanutilsLogWriter(
                            self.record_dir / f"{vehicle.name}.log", channel=vehicle.name
                        )
                        self._writers.append(writer)
                        vehicle.taps.append(writer.on_message_received)
            except BaseException:
                self._close_all()
                raise
            self._opened = True
            self.t0 = self.clock.now()
            for vehicle in self.vehicles.values():
                vehicle.start(self.t0)
                vehicle.advance_to(self.t0, self._events_for)

    def close(self) -> None:
        """Stop any runner, close buses and log files."""
        self.stop_thread()
        with self._lock:
            self._close_all()
            self._opened = False

    def _close_all(self) -> None:
        for vehicle in self.vehicles.values():
            vehicle.taps.clear()
            vehicle.close()
        for writer in self._writers:
            writer.stop()
        self._writers.clear()

    def __enter__(self) -> SimulatedFleet:
        self.open()
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()

    async def __aenter__(self) -> SimulatedFleet:
        await self.start()
        return self

    async def __aexit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        await self.stop()

    # ----- running ----------------------------------------------------------------------------
    def run_until(self, t: float, *, lazy: bool = False) -> None:
        """Run every vehicle up to simulated time `t` (`lazy`: see `advance_to`)."""
        if not self._opened:
            self.open()
        with self._lock:
            for vehicle in self.vehicles.values():
                vehicle.advance_to(t, self._events_for, lazy=lazy)

    def advance(self, seconds: float) -> float:
        """Step a manual clock by `seconds` and run the fleet to the new time (tests)."""
        if not isinstance(self.clock, ManualClock):
            raise TypeError("advance() needs a ManualClock; a real-time fleet runs by itself")
        if not self._opened:
            self.open()
        with self._lock:
            now = self.clock.advance(seconds)
            self.run_until(now)
        return now

    def poll(self) -> None:
        """Handle frames sent to the fleet since the last step, without moving time."""
        self.run_until(self.clock.now())

    def tick(self) -> None:
        """One real-time step: catch up with the clock (idle vehicles wait for their next due).

        With an end set (`run_for`), no vehicle runs past it, and the step that reaches it runs
        every vehicle to exactly the end (idle ones included): `finished` then holds."""
        now = self.clock.now()
        end = self.end
        if end is not None and now >= end:
            if not self._finished:
                self.run_until(end)
                self._finished = True
            return
        self.run_until(now, lazy=True)
        if self._writers and time.monotonic() - self._flushed_at >= RECORD_FLUSH_S:
            self._flush_records()

    def _flush_records(self) -> None:
        """Hand what the recording's files buffer to the OS (python-can's writers buffer 8 KB:
        minutes of one vehicle's frames)."""
        with self._lock:
            for writer in self._writers:
                writer.file.flush()
        self._flushed_at = time.monotonic()

    def run_for(self, seconds: float) -> None:
        """End the run `seconds` simulated seconds after the start (a real-time clock)."""
        if seconds < 0 or seconds != seconds:
            raise ValueError("the duration must be a non-negative number of seconds")
        self.duration = seconds

    @property
    def end(self) -> float | None:
        """The simulated time the run ends at, once started with `run_for`."""
        if self.duration is None or self.t0 is None:
            return None
        return self.t0 + self.duration

    @property
    def finished(self) -> bool:
        """Every vehicle has been simulated up to the end set by `run_for`."""
        return self._finished

    @property
    def simulated(self) -> float:
        """Simulated seconds every vehicle has been run through (the slowest one's)."""
        if self.t0 is None or not self.vehicles:
            return 0.0
        with self._lock:
            return min(v.t for v in self.vehicles.values()) - self.t0

    async def start(self) -> None:
        """Open the buses and, on a real-time clock, run the fleet as an asyncio task."""
        self.open()
        if not self.clock.stepped and self._task is None:
            self._task = asyncio.create_task(self._run_async(), name="eqgw-sim-fleet")

    async def stop(self) -> None:
        task, self._task = self._task, None
        if task is not None:
            await cancel_and_wait(task)
        self.close()

    async def _run_async(self) -> None:
        try:
            while True:
                self.tick()
                await asyncio.sleep(self.tick_s)
        except asyncio.CancelledError:
            raise
        except Exception as exc:  # surfaced to the owner through .error
            self.error = exc

    def start_thread(self) -> None:
        """Open the buses and run the fleet on a daemon thread (real-time clock)."""
        if self.clock.stepped:
            raise TypeError("a stepped clock does not run by itself; call advance()")
        self.open()
        if self._thread is None:
            self._stop.clear()
            self._thread = threading.Thread(
                target=self._run_thread, name="eqgw-sim-fleet", daemon=True
            )
            self._thread.start()

    def stop_thread(self) -> None:
        thread, self._thread = self._thread, None
        if thread is not None:
            self._stop.set()
            thread.join(timeout=10)

    def _run_thread(self) -> None:
        try:
            while not self._stop.is_set():
                self.tick()
                self._stop.wait(self.tick_s)
        except Exception as exc:  # surfaced to the owner through .error
            self.error = exc

    # ----- scripted events --------------------------------------------------------------------
    def _events_for(self, vehicle: SimulatedVehicle, t: float) -> float:
        """Apply the vehicle's scenario events due at `t`; return when the next one is due."""
        pending = self._pending[vehicle.name]
        t0 = self.t0 if self.t0 is not None else t
        while pending and t0 + pending[0].at <= t + 1e-9:
            event = pending.pop(0)
            apply_action(vehicle, event.action, dict(event.args))
        return t0 + pending[0].at if pending else math.inf

    def schedule(self, at: float, vehicle: str, action: str, **args: Any) -> None:
        """Script an action `at` simulated seconds after the start (like a scenario event)."""
        event = Event(at, vehicle, action, args)
        targets = self.names if vehicle == "all" else [self.vehicle(vehicle).name]
        with self._lock:
            for name in targets:
                pending = self._pending[name]
                pending.append(event)
                pending.sort(key=lambda e: e.at)

    # ----- event injection (thread-safe; applied at the fleet's present time) ----------------
    def inject(self, vehicle: str, action: str, **args: Any) -> Any:
        """Apply a scenario action now, e.g. `inject("SIM-001", "add_12v_load", amps=80)`."""
        Event(0.0, vehicle, action, args)  # validates the action and its arguments
        with self._lock:
            target = self.vehicle(vehicle)
            if not self.clock.stepped and not math.isnan(target.t):
                # A real-time vehicle may be idling behind the clock (lazy ticks): catch up.
                target.advance_to(self.clock.now(), self._events_for)
            return apply_action(target, action, args)

    def add_12v_load(self, vehicle: str, amps: float, name: str | None = None) -> str:
        """Switch on a 12 V load; returns the name to switch it off with."""
        result: str = self.inject(vehicle, "add_12v_load", amps=amps, name=name)
        return result

    def remove_12v_load(self, vehicle: str, name: str | None = None) -> None:
        self.inject(vehicle, "remove_12v_load", name=name)

    def add_24v_load(self, vehicle: str, amps: float, name: str | None = None) -> str:
        result: str = self.inject(vehicle, "add_24v_load", amps=amps, name=name)
        return result

    def remove_24v_load(self, vehicle: str, name: str | None = None) -> None:
        self.inject(vehicle, "remove_24v_load", name=name)

    def alternator_off(self, vehicle: str) -> None:
        self.inject(vehicle, "alternator_off")

    def alternator_on(self, vehicle: str, volts: float | None = None) -> None:
        self.inject(vehicle, "alternator_on", volts=volts)

    def jump_start(self, vehicle: str, volts: float = 27.0) -> None:
        self.inject(vehicle, "jump_start", volts=volts)

    def end_jump_start(self, vehicle: str) -> None:
        self.inject(vehicle, "end_jump_start")

    def fail_battery_b(self, vehicle: str) -> None:
        self.inject(vehicle, "fail_battery_b")

    def restore_battery_b(self, vehicle: str) -> None:
        self.inject(vehicle, "restore_battery_b")

    def fail_equalizer(self, vehicle: str, sa: int | None = None) -> None:
        self.inject(vehicle, "fail_equalizer", sa=sa)

    def restore_equalizer(self, vehicle: str, sa: int | None = None) -> None:
        self.inject(vehicle, "restore_equalizer", sa=sa)

    def stop_heartbeat(self, vehicle: str, sa: int | None = None, mode: str = "stuck") -> None:
        self.inject(vehicle, "stop_heartbeat", sa=sa, mode=mode)

    def restore_heartbeat(self, vehicle: str, sa: int | None = None) -> None:
        self.inject(vehicle, "restore_heartbeat", sa=sa)

    def disconnect_bus(self, vehicle: str) -> None:
        self.inject(vehicle, "disconnect_bus")

    def reconnect_bus(self, vehicle: str) -> None:
        self.inject(vehicle, "reconnect_bus")

    def ignition_off(self, vehicle: str) -> None:
        self.inject(vehicle, "ignition_off")

    def ignition_on(self, vehicle: str) -> None:
        self.inject(vehicle, "ignition_on")

    def disconnect_unit(self, vehicle: str, sa: int | None = None) -> None:
        self.inject(vehicle, "disconnect_unit", sa=sa)

    def reconnect_unit(self, vehicle: str, sa: int | None = None) -> None:
        self.inject(vehicle, "reconnect_unit", sa=sa)

    def add_tap(self, vehicle: str, tap: Callable[[can.Message], None]) -> None:
        """Call `tap(msg)` for every frame on the vehicle's bus, stamped with simulated time."""
        with self._lock:
            self.vehicle(vehicle).taps.append(tap)


def apply_action(vehicle: SimulatedVehicle, action: str, args: dict[str, Any]) -> Any:
    """Call the vehicle method an action names, dropping arguments left as None."""
    method = getattr(vehicle, action)
    return method(**{k: v for k, v in args.items() if v is not None})
