"""Electrical model of a 24/12 V battery system with VANN-Guard equalizers (Theory of Operation).

Battery A sits between ground and the +12 V tap, battery B between +12 V and +24 V. The alternator
(or a jump-start source) feeds +24 V, 24 V loads hang across both batteries, 12 V loads across
battery A. The equalizers move current from +24 V to +12 V so that B - A stays just above 0.05 V
when running: "within 0.05 V under light loads and within 0.1 V at full rated load". Every
quantity is solved quasi-statically per step (the circuit is linear once the sources are fixed)
and the state of charge integrates the battery currents. Currents are positive into a battery.
"""

from __future__ import annotations

from bisect import bisect_right
from dataclasses import dataclass, field

# Resting voltage against state of charge for a 12 V lead-acid battery; below a few percent it
# collapses, which is how a "completely dead" battery A drains toward zero in the no-start story.
_OCV_POINTS: tuple[tuple[float, float], ...] = (
    (0.0, 2.0),
    (0.03, 10.5),
    (0.10, 11.80),
    (0.50, 12.20),
    (0.75, 12.45),
    (1.00, 12.75),
)
_OCV_SOC = [p[0] for p in _OCV_POINTS]

# The equalizer turns on when A is more than this below B (troubleshooting table row a) ...
STANDBY_THRESHOLD_V = 0.05
# ... and lets B - A grow by this much more at full rated current (row b, 0.05..0.10 V).
REGULATION_SPAN_V = 0.05
# Shutdown limits of both manuals: system below 16 V or either battery below 8 V.
SHUTDOWN_SYSTEM_V = 16.0
SHUTDOWN_BATTERY_V = 8.0
# With jump-start override the unit keeps running down to this (it needs some supply to work).
JSO_MIN_BATTERY_V = 4.0
EFFICIENCY = 0.97
CHARGE_EFFICIENCY = 0.95
# A shorted cell takes about one cell's voltage off the battery.
SHORTED_CELL_V = 2.1


def ocv(soc: float) -> float:
    """Open-circuit voltage of a healthy 12 V battery at this state of charge (0..1)."""
    soc = min(1.0, max(0.0, soc))
    i = bisect_right(_OCV_SOC, soc)
    if i >= len(_OCV_POINTS):
        return _OCV_POINTS[-1][1]
    (s0, v0), (s1, v1) = _OCV_POINTS[i - 1], _OCV_POINTS[i]
    return v0 + (v1 - v0) * (soc - s0) / (s1 - s0)


@dataclass(slots=True)
class Battery:
    """One 12 V battery (or bank): charge state, health and internal resistance."""

    capacity_ah: float = 200.0
    soc: float = 0.9
    soh: float = 1.0
    r_ohm: float = 0.006
    ocv_offset_v: float = 0.0  # negative for a shorted cell

    def ocv(self) -> float:
        return ocv(self.soc) + self.ocv_offset_v

    def resistance(self, charging: bool) -> float:
        """Internal resistance; charge acceptance falls steeply as the battery fills."""
        if charging:
            return self.r_ohm * (1.0 + 25.0 * self.soc**4)
        # A discharged or worn battery sags more under load.
        return self.r_ohm * (1.0 + 2.0 * (1.0 - self.soc) ** 2) / max(self.soh, 0.2)

    def integrate(self, amps: float, seconds: float) -> None:
        """Move the state of charge by `amps` (positive charging) for `seconds`."""
        usable_ah = self.capacity_ah * max(self.soh, 0.05)
        eff = CHARGE_EFFICIENCY if amps > 0 else 1.0
        self.soc = min(1.0, max(0.0, self.soc + amps * eff * seconds / 3600.0 / usable_ah))


@dataclass(slots=True)
class Source:
    """A regulated 24 V source: the alternator or a jump-start pack."""

    on: bool = False
    volts: float = 28.2
    max_amps: float = 150.0


@dataclass(slots=True)
class Stage:
    """The power stage of one equalizer unit (the CAN side lives in equalizer.py)."""

    rating_a: float
    available: bool = True  # on, not failed, not shut down: set by the unit each step
    amps: float = 0.0  # output into +12 V from the last solve


@dataclass(slots=True)
class Solution:
    """Node voltages and branch currents of one solve."""

    v12: float
    v24: float
    ia: float
    ib: float
    i_eq: float
    i_source: float

    @property
    def va(self) -> float:
        return self.v12

    @property
    def vb(self) -> float:
        return self.v24 - self.v12


@dataclass
class ElectricalSystem:
    """A vehicle's battery system: batteries, loads, sources and the equalizer stages."""

    a: Battery = field(default_factory=Battery)
    b: Battery = field(default_factory=Battery)
    alternator: Source = field(default_factory=Source)
    jump: Source = field(default_factory=lambda: Source(on=False, volts=27.0, max_amps=400.0))
    loads_12v: dict[str, float] = field(default_factory=dict)
    loads_24v: dict[str, float] = field(default_factory=dict)
    # 12 V loads wrongly wired across battery B (troubleshooting row e).
    loads_on_b: dict[str, float] = field(default_factory=dict)
    stages: list[Stage] = field(default_factory=list)
    temperature_c: float = 20.0
    last: Solution | None = None

    def __post_init__(self) -> None:
        if self.last is None:
            va, vb = self.a.ocv(), self.b.ocv()
            self.last = Solution(va, va + vb, 0.0, 0.0, 0.0, 0.0)

    @property
    def solution(self) -> Solution:
        assert self.last is not None
        return self.last

    def _load_amps(self) -> tuple[float, float, float]:
        # Loads behave resistively below their nominal voltage, so a dead battery is not
        # driven negative by a constant-current load.
        s = self.solution
        f12 = min(1.0, max(0.0, s.va / 12.0))
        f24 = min(1.0, max(0.0, s.v24 / 24.0))
        fb = min(1.0, max(0.0, s.vb / 12.0))
        return (
            sum(self.loads_12v.values()) * f12,
            sum(self.loads_24v.values()) * f24,
            sum(self.loads_on_b.values()) * fb,
        )

    def _source(self) -> Source | None:
        on = [s for s in (self.alternator, self.jump) if s.on]
        return max(on, key=lambda s: s.volts) if on else None

    def _eq_limit(self) -> tuple[float, float]:
        """(current limit, nominal rating) of the stages that can run right now."""
        rating = sum(s.rating_a for s in self.stages if s.available)
        diff = self.solution.vb - self.solution.va
        # Full rated output while the batteries stay within 0.10 V; the protection circuits
        # fold it back as they drift further apart (Overload Condition).
        over = max(0.0, diff - (STANDBY_THRESHOLD_V + REGULATION_SPAN_V))
        derate = max(0.5, 1.0 - over / 8.0)
        return rating * derate, rating

    def solve(self) -> Solution:
        """Solve the circuit for the present state, choosing the equalizer current."""
        prev = self.solution
        # Resistance depends on the direction of each battery's current: start from the last
        # solve's directions and redo once if a battery turned around.
        charging = (prev.ia > 0.0, prev.ib > 0.0)
        sol = self._solve(*charging)
        turned = (sol.ia > 0.0, sol.ib > 0.0)
        if turned != charging:
            sol = self._solve(*turned)
        self._share(sol.i_eq)
        self.last = sol
        return sol

    def _solve(self, a_charging: bool, b_charging: bool) -> Solution:
        l12, l24, lb = self._load_amps()
        src = self._source()
        ra = self.a.resistance(a_charging)
        rb = self.b.resistance(b_charging)
        oa, ob = self.a.ocv(), self.b.ocv()
        k = 0.5 / EFFICIENCY  # input amps at +24 V per output amp at +12 V

        def branch(i_eq: float, i_src: float | None) -> Solution:
            # i_src None: the source holds its voltage; otherwise it delivers i_src amps.
            if i_src is None:
                assert src is not None
                ib = (src.volts - oa - ob - ra * (i_eq + lb - l12)) / (ra + rb)
                i_src = l24 + ib + k * i_eq + lb
            else:
                ib = i_src - l24 - k * i_eq - lb
            ia = ib + i_eq + lb - l12
            va = oa + ra * ia
            vb = ob + rb * ib
            return Solution(va, va + vb, ia, ib, i_eq, i_src)

        def pick_mode(i_eq: float) -> float | None:
            if src is None:
                return 0.0
            s = branch(i_eq, None)
            if s.i_source > src.max_amps:
                return src.max_amps
            if s.i_source < 0.0:
                return 0.0  # batteries above the regulator: the source idles
            return None

        limit, rating = self._eq_limit()
        i_eq = 0.0
        mode = pick_mode(0.0)
        if rating > 0.0:
            for _ in range(3):
                s0, s1 = branch(0.0, mode), branch(1.0, mode)
                d0 = s0.vb - s0.va
                slope = (s1.vb - s1.va) - d0  # volts of B - A per equalizer amp (negative)
                if d0 <= STANDBY_THRESHOLD_V:
                    i_eq = 0.0
                else:
                    # Regulate B - A to 0.05 V + 0.05 V * (I / rating).
                    i_eq = (d0 - STANDBY_THRESHOLD_V) / (REGULATION_SPAN_V / rating - slope)
                    i_eq = min(max(i_eq, 0.0), limit)
                new_mode = pick_mode(i_eq)
                if new_mode == mode:
                    break
                mode = new_mode
        return branch(i_eq, mode)

    def _share(self, i_eq: float) -> None:
        running = [s for s in self.stages if s.available]
        total = sum(s.rating_a for s in running)
        for s in self.stages:
            s.amps = i_eq * s.rating_a / total if s.available and total > 0 else 0.0

    def step(self, seconds: float) -> Solution:
        """Solve at the present state, then let `seconds` pass at those currents."""
        sol = self.solve()
        if seconds > 0:
            self.a.integrate(sol.ia, seconds)
            self.b.integrate(sol.ib, seconds)
        return sol


def classify(sol: Solution, running: bool) -> str:
    """Troubleshooting-table row for a reading: standby, normal, overload, not_functioning,
    abnormal."""
    diff = sol.vb - sol.va
    if diff < -STANDBY_THRESHOLD_V:
        return "abnormal"  # A above B: suspect battery B or a 12 V load on B
    if diff <= STANDBY_THRESHOLD_V + 1e-9:
        return "standby"
    if diff <= STANDBY_THRESHOLD_V + REGULATION_SPAN_V + 1e-9:
        return "normal" if running else "not_functioning"
    return "overload" if running else "not_functioning"
