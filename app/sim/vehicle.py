"""One simulated vehicle: its battery system, its equalizer units and its CAN bus."""

from __future__ import annotations

import math
import random
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import can

from eqgw.protocol.decode import FrameDecoder
from eqgw.sim.background import BackgroundTraffic
from eqgw.sim.equalizer import EqualizerSpec, SimulatedEqualizer
from eqgw.sim.model import SHORTED_CELL_V, Battery, ElectricalSystem, Solution, Source, classify

# The quasi-static model is re-solved at least this often even when no frame is due, so that
# fault thresholds are crossed on time.
MAX_STEP_S = 0.5
Tap = Callable[[can.Message], None]


@dataclass
class VehicleSpec:
    """How a simulated vehicle starts: its units, batteries, loads and charging."""

    name: str
    units: list[EqualizerSpec] = field(default_factory=lambda: [EqualizerSpec()])
    battery_ah: float = 200.0
    soc_a: float = 0.9
    soc_b: float = 0.9
    soh_a: float = 1.0
    soh_b: float = 1.0
    load_12v_a: float = 10.0
    load_24v_a: float = 5.0
    alternator_on: bool = True
    alternator_v: float = 28.2
    alternator_max_a: float = 150.0
    temperature_c: float = 20.0
    request_byte_order: str = "lsb"

    def __post_init__(self) -> None:
        sas = [u.sa for u in self.units]
        if not sas:
            raise ValueError(f"{self.name}: a vehicle needs at least one equalizer")
        if len(set(sas)) != len(sas):
            raise ValueError(f"{self.name}: equalizer source addresses must differ: {sas}")
        for what in ("soc_a", "soc_b", "soh_a", "soh_b"):
            value = getattr(self, what)
            if not 0.0 <= value <= 1.0:
                raise ValueError(f"{self.name}: {what} {value} is not 0..1")
        if self.request_byte_order not in ("lsb", "msb"):
            raise ValueError(f"{self.name}: request_byte_order is 'lsb' or 'msb'")

    def describe(self) -> dict[str, Any]:
        """What the CLI prints and the demo shows: name and each unit's SA, series and model."""
        return {
            "name": self.name,
            "units": [{"sa": u.sa, "series": u.series, "model": u.model} for u in self.units],
        }


class SimulatedVehicle:
    """A vehicle's electrical system and equalizers, stepping in simulated time on its bus."""

    def __init__(
        self,
        spec: VehicleSpec,
        channel: str,
        *,
        rng: random.Random,
        background_traffic: bool = False,
    ) -> None:
        self.spec = spec
        self.name = spec.name
        self.channel = channel
        self.system = ElectricalSystem(
            a=Battery(capacity_ah=spec.battery_ah, soc=spec.soc_a, soh=spec.soh_a),
            b=Battery(capacity_ah=spec.battery_ah, soc=spec.soc_b, soh=spec.soh_b),
            alternator=Source(
                on=spec.alternator_on, volts=spec.alternator_v, max_amps=spec.alternator_max_a
            ),
            loads_12v={"base": spec.load_12v_a} if spec.load_12v_a else {},
            loads_24v={"base": spec.load_24v_a} if spec.load_24v_a else {},
            temperature_c=spec.temperature_c,
        )
        self.units: list[SimulatedEqualizer] = [
            SimulatedEqualizer(
                u,
                self.system,
                self.transmit,
                phase_status=rng.uniform(0.0, 3.0),
                phase_battery=rng.uniform(0.0, 5.0),
            )
            for u in spec.units
        ]
        self._decoder = FrameDecoder(
            equalizer_sas=[u.sa for u in spec.units],
            request_byte_order=spec.request_byte_order,
            only=("control", "parameters", "request"),
        )
        self.background = (
            BackgroundTraffic(
                rng, lambda: self.system.alternator.on, lambda: self.system.solution.v24
            )
            if background_traffic
            else None
        )
        self.bus: can.BusABC | None = None
        self.connected = True
        self.ignition = True
        self._alternator_before_off = spec.alternator_on
        self._cut_sas: set[int] = set()  # units whose own CAN wiring is cut
        self.t = math.nan
        self.taps: list[Tap] = []
        self.frames_sent = 0
        self.frames_received = 0
        self._load_seq = 0

    # ----- bus --------------------------------------------------------------------------------
    def open(self) -> None:
        """Attach to the vehicle's python-can virtual channel."""
        if self.bus is None:
            self.bus = can.Bus(
                interface="virtual",
                channel=self.channel,
                receive_own_messages=False,
                preserve_timestamps=True,
            )

    def close(self) -> None:
        if self.bus is not None:
            self.bus.shutdown()
            self.bus = None

    def transmit(self, ts: float, can_id: int, data: bytes) -> None:
        """Put one frame on the bus at simulated time `ts` (dropped while disconnected, with
        the ignition off, or from a unit whose own wiring is cut)."""
        if not self.connected or not self.ignition:
            return
        if self._cut_sas and (can_id & 0xFF) in self._cut_sas:
            return
        msg = can.Message(
            timestamp=ts,
            arbitration_id=can_id,
            is_extended_id=True,
            data=data,
            channel=self.name,
            is_rx=False,
        )
        if self.bus is not None:
            self.bus.send(msg)
        self.frames_sent += 1
        for tap in self.taps:
            tap(msg)

    def _poll(self) -> None:
        self._handle(self._drain())

    def _drain(self) -> list[can.Message]:
        """Frames sent to this vehicle since the last look (none while the wires are cut)."""
        bus = self.bus
        inbox: list[can.Message] = []
        if bus is None:
            return inbox
        while True:
            msg = bus.recv(timeout=0)
            if msg is None:
                return inbox
            if self.connected and self.ignition:
                inbox.append(msg)

    def _handle(self, inbox: list[can.Message]) -> None:
        for msg in inbox:
            self.frames_received += 1
            # Frames from others carry their sender's clock; the log and the units use ours.
            msg.timestamp = self.t
            msg.channel = self.name
            for tap in self.taps:
                tap(msg)
            for record in self._decoder.decode_message(msg):
                for unit in self.units:
                    if unit.spec.sa not in self._cut_sas:
                        unit.handle(self.t, record)

    # ----- time -------------------------------------------------------------------------------
    def start(self, t: float) -> None:
        """Power up at simulated time `t`."""
        self.t = t
        self._resolve()
        for unit in self.units:
            unit.start(t)
        if self.background is not None:
            self.background.start(t)

    def _resolve(self) -> Solution:
        for unit in self.units:
            unit.prepare()
        sol = self.system.solve()
        # A unit's availability depends on the voltages it just helped set; settle once.
        for unit in self.units:
            unit.prepare()
        return sol

    def next_wakeup(self) -> float:
        times = [unit.next_wakeup() for unit in self.units]
        if self.background is not None:
            times.append(self.background.next_wakeup())
        return min(times)

    def advance_to(
        self,
        target: float,
        events: Callable[[SimulatedVehicle, float], float] | None = None,
        *,
        lazy: bool = False,
    ) -> None:
        """Run the vehicle up to simulated time `target`.

        `events(vehicle, t)` applies scripted events due at `t` and returns when the next is due.
        `lazy` (real-time ticks): when no frame arrived and nothing is due before `target`, the
        vehicle stays where it is; the next step integrates over the whole gap (at most
        MAX_STEP_S), so 200 idle vehicles do not each solve their circuit 50 times a second.
        """
        if math.isnan(self.t):
            self.start(target)
        if not lazy:
            self._poll()
            self._run_to(target, events)
            return
        inbox = self._drain()
        if not inbox:
            due = min(self.t + MAX_STEP_S, self.next_wakeup())
            if events:
                due = min(due, events(self, self.t))
            if target < due:
                return
        self._run_to(target, events)
        if inbox:
            # Handled at the time they were seen, after the vehicle caught up with it.
            self._handle(inbox)
            self._run_to(target, events)

    def _run_to(
        self, target: float, events: Callable[[SimulatedVehicle, float], float] | None
    ) -> None:
        next_event = events(self, self.t) if events else math.inf
        while True:
            nxt = min(target, self.t + MAX_STEP_S, self.next_wakeup(), next_event)
            if nxt > self.t:
                sol = self.system.solution
                dt = nxt - self.t
                self.system.a.integrate(sol.ia, dt)
                self.system.b.integrate(sol.ib, dt)
                self.t = nxt
            if events:
                next_event = events(self, self.t)
            sol = self._resolve()
            for unit in self.units:
                unit.update(self.t, sol)
            if self.background is not None:
                self.background.update(self.t, self.transmit)
            if self.t >= target:
                return
            if self.next_wakeup() <= self.t:
                # Everything due now has run; a schedule that did not move would spin.
                raise RuntimeError(f"{self.name}: schedule stuck at t={self.t}")

    # ----- readings ---------------------------------------------------------------------------
    @property
    def solution(self) -> Solution:
        return self.system.solution

    def unit(self, sa: int | None = None) -> SimulatedEqualizer:
        """The unit at `sa` (default: the first)."""
        if sa is None:
            return self.units[0]
        for unit in self.units:
            if unit.sa == sa:
                return unit
        raise KeyError(f"{self.name} has no equalizer at SA {sa}")

    def _units(self, sa: int | None) -> list[SimulatedEqualizer]:
        return self.units if sa is None else [self.unit(sa)]

    def condition(self) -> str:
        """Troubleshooting-table row for the present readings."""
        return classify(self.solution, any(u.running for u in self.units))

    # ----- events -----------------------------------------------------------------------------
    def add_12v_load(self, amps: float, name: str | None = None) -> str:
        """Switch on a 12 V load (on battery A); returns its name for `remove_12v_load`."""
        return self._add_load(self.system.loads_12v, amps, name)

    def remove_12v_load(self, name: str | None = None) -> None:
        """Switch off one added 12 V load, or every added one."""
        self._remove_load(self.system.loads_12v, name)

    def add_24v_load(self, amps: float, name: str | None = None) -> str:
        """Switch on a 24 V load; returns its name."""
        return self._add_load(self.system.loads_24v, amps, name)

    def remove_24v_load(self, name: str | None = None) -> None:
        self._remove_load(self.system.loads_24v, name)

    def add_load_on_b(self, amps: float, name: str | None = None) -> str:
        """A 12 V load wrongly wired across battery B (troubleshooting row e)."""
        return self._add_load(self.system.loads_on_b, amps, name)

    def remove_load_on_b(self, name: str | None = None) -> None:
        self._remove_load(self.system.loads_on_b, name)

    def _add_load(self, loads: dict[str, float], amps: float, name: str | None) -> str:
        if amps < 0:
            raise ValueError("load current must not be negative")
        if name is None:
            self._load_seq += 1
            name = f"load-{self._load_seq}"
        loads[name] = float(amps)
        self._settle()
        return name

    def _remove_load(self, loads: dict[str, float], name: str | None) -> None:
        if name is None:
            for key in [k for k in loads if k != "base"]:
                del loads[key]
        else:
            loads.pop(name, None)
        self._settle()

    def set_base_loads(self, load_12v: float | None = None, load_24v: float | None = None) -> None:
        """Change the vehicle's standing loads."""
        if load_12v is not None:
            self.system.loads_12v["base"] = float(load_12v)
        if load_24v is not None:
            self.system.loads_24v["base"] = float(load_24v)
        self._settle()

    def alternator_off(self) -> None:
        """Engine stopped: no charging."""
        self.system.alternator.on = False
        self._settle()

    def alternator_on(self, volts: float | None = None) -> None:
        """Engine running: the alternator holds `volts` (default: as built) at +24 V."""
        self.system.alternator.on = True
        if volts is not None:
            self.system.alternator.volts = float(volts)
        self._settle()

    def jump_start(self, volts: float = 27.0) -> None:
        """Connect a jump-start source across the 24 V string."""
        self.system.jump.on = True
        self.system.jump.volts = float(volts)
        self._settle()

    def end_jump_start(self) -> None:
        self.system.jump.on = False
        self._settle()

    def fail_battery_b(self) -> None:
        """Battery B develops a shorted cell: a volt or two low, little capacity left."""
        b = self.system.b
        b.ocv_offset_v = -SHORTED_CELL_V
        b.soh = min(b.soh, 0.35)
        self._settle()

    def restore_battery_b(self) -> None:
        """Battery B replaced by a healthy one at the same charge."""
        b = self.system.b
        b.ocv_offset_v = 0.0
        b.soh = self.spec.soh_b
        self._settle()

    def set_soc(self, a: float | None = None, b: float | None = None) -> None:
        """Set the batteries' state of charge (0..1)."""
        if a is not None:
            self.system.a.soc = min(1.0, max(0.0, float(a)))
        if b is not None:
            self.system.b.soc = min(1.0, max(0.0, float(b)))
        self._settle()

    def set_temperature(self, celsius: float) -> None:
        self.system.temperature_c = float(celsius)

    def fail_equalizer(self, sa: int | None = None) -> None:
        """The power stage of one unit (default: every unit) stops transferring current."""
        for unit in self._units(sa):
            unit.failed = True
        self._settle()

    def restore_equalizer(self, sa: int | None = None) -> None:
        for unit in self._units(sa):
            unit.failed = False
        self._settle()

    def stop_heartbeat(self, sa: int | None = None, mode: str = "stuck") -> None:
        """The monitor's heartbeat stops alternating (`stuck`) or stops being sent (`silent`)."""
        if mode not in ("stuck", "silent"):
            raise ValueError("heartbeat mode is 'stuck' or 'silent'")
        for unit in self._units(sa):
            unit.heartbeat_mode = mode

    def restore_heartbeat(self, sa: int | None = None) -> None:
        for unit in self._units(sa):
            unit.heartbeat_mode = "normal"

    def ignore_commands(self, sa: int | None = None) -> None:
        """One unit (default: every unit) stops acting on control, parameter and request
        frames: its receive path has failed while it still transmits."""
        for unit in self._units(sa):
            unit.deaf = True

    def obey_commands(self, sa: int | None = None) -> None:
        for unit in self._units(sa):
            unit.deaf = False

    def disconnect_bus(self) -> None:
        """The vehicle's CAN wiring is cut: nothing is sent or received until reconnected."""
        self.connected = False

    def reconnect_bus(self) -> None:
        self.connected = True

    def ignition_off(self) -> None:
        """The driver switches off: the engine stops (no charging, the standing loads stay)
        and every node on the bus, the equalizers and the engine's and transmission's
        controllers included, powers down: the whole bus is silent until `ignition_on`."""
        if self.ignition:
            self._alternator_before_off = self.system.alternator.on
        self.ignition = False
        self.system.alternator.on = False
        self._settle()

    def ignition_on(self) -> None:
        """The driver switches on: every node talks again and the engine runs as before."""
        if not self.ignition:
            self.system.alternator.on = self._alternator_before_off
        self.ignition = True
        self._settle()

    def disconnect_unit(self, sa: int | None = None) -> None:
        """One unit's (default: every unit's) own CAN wiring is cut: it sends and hears
        nothing while the rest of the bus carries on."""
        for unit in self._units(sa):
            self._cut_sas.add(unit.spec.sa)

    def reconnect_unit(self, sa: int | None = None) -> None:
        for unit in self._units(sa):
            self._cut_sas.discard(unit.spec.sa)

    def _settle(self) -> None:
        # Readings change at once when a load or a source does; the units see them next step.
        if not math.isnan(self.t):
            self._resolve()
