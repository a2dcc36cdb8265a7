"""One simulated VANN-Guard unit: its Smart Monitor's CAN behaviour as both manuals describe it.

The unit broadcasts status, heartbeat and voltages every 3 s and (80-series) battery states every
5 s, raises OVF/UVF/IMB/EQFLT after the fault timer, reports them by DM1 under the manuals' rules,
answers requests, obeys control commands and takes parameter writes. Its power stage is a
`model.Stage` the vehicle's electrical model drives.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from eqgw.protocol.dm1 import NAMED_CODES
from eqgw.protocol.encode import encode
from eqgw.protocol.j1939 import (
    GLOBAL_ADDRESS,
    PGN_COMPONENT_ID,
    PGN_COMPONENT_ID_70_MISPRINT,
    PGN_DM1,
    PGN_SOFTWARE_ID,
    compose_id,
)
from eqgw.protocol.records import Record
from eqgw.sim.clock import next_after
from eqgw.sim.model import (
    JSO_MIN_BATTERY_V,
    SHUTDOWN_BATTERY_V,
    SHUTDOWN_SYSTEM_V,
    ElectricalSystem,
    Solution,
    Stage,
)

Frame = tuple[int, bytes]
Transmit = Callable[[float, int, bytes], None]

STATUS_PERIOD_S = 3.0
BATTERY_STATES_PERIOD_S = 5.0
DM1_PERIOD_S = 1.0
# No more than one state change per DTC per second (DM1 criteria).
DTC_CHANGE_GUARD_S = 1.0
# BAM data packets follow the announcement 50 ms apart (J1939-21 allows 50..200 ms).
BAM_PACKET_GAP_S = 0.05
# The manuals do not say what imbalance raises IMB; half a volt between A and B is far outside
# the 0.1 V the equalizer holds at full load.
IMB_THRESHOLD_V = 0.5
HYSTERESIS_V = 0.2
RUNNING_MIN_A = 0.001  # any transfer at all: B - A is then above 0.05 V
DTC_ORDER = ("OVF", "UVF", "IMB", "EQFLT")
OC_MAX = 126  # 127 means "not available" in J1939-73

MODELS = {60: "60CAN", 80: "80CAN", 100: "100CAN"}

# Defaults after a factory reset. OV/UV/timer are not printed in the manuals: these are the
# simulator's choice (OV above a 28.2 V alternator, UV near 30 % charge at rest).
DEFAULTS_9: dict[str, float] = {"ov_setpoint_v": 30.0, "uv_setpoint_v": 24.0, "fault_timer_s": 10}
DEFAULTS_80: dict[str, float] = {
    "cells": 12,
    "charge_efficiency_pct": 95.0,
    "peukert_capacity_ah": 200.0,
    "peukert_exponent": 1.2,
    "temp_constant": 0.01,
    "rated_temp_c": 25.0,
    "endpoint_v": 10.5,
    "charge_threshold_a": 5.0,
    "discharge_threshold_a": -5.0,
    "boost_charge_threshold_a": 50.0,
    "start_threshold_a": 150.0,
    "cold_start_threshold_a": 300.0,
    "capacity_ah": 200.0,
    "cranking_current_a": 350.0,
    "voltage_trip_v": 1.25,
    "c_rating": 10.0,
    "current_low_fsd_a": 80.0,
    "current_high_fsd_a": 600.0,
    "calibration": 2,
}
SERIES_70_INDEXES = frozenset({0, 9})
SERIES_80_INDEXES = frozenset(range(0, 11))
# Largest run time the 0.5 min/bit field carries (raw 0xFAFF).
RUNTIME_MAX_MIN = 0xFAFF * 0.5


def model_name(series: int, rating_a: int) -> str:
    """Catalogue model number, e.g. `80-100CAN`."""
    return f"{series}-{MODELS[rating_a]}"


@dataclass(slots=True)
class DtcState:
    """One DTC: raw condition, fault timer, the state reported by DM1 and its occurrence count."""

    condition_since: float | None = None
    reported: bool = False
    last_change: float = -math.inf
    occurrences: int = 0


@dataclass(slots=True)
class _Outgoing:
    due: float
    can_id: int
    data: bytes


@dataclass
class EqualizerSpec:
    """What a unit is: series, rating, source address and identification revisions."""

    sa: int = 30
    series: int = 80
    rating_a: int = 100
    hardware_revision: int = 1
    software_revision: int = 1

    def __post_init__(self) -> None:
        if self.series not in (70, 80):
            raise ValueError(f"series {self.series} is not 70 or 80")
        if self.rating_a not in MODELS:
            raise ValueError(f"rating {self.rating_a} A is not one of {sorted(MODELS)}")
        if not 0 <= self.sa <= 253:
            raise ValueError(f"source address {self.sa} is not 0..253")

    @property
    def model(self) -> str:
        return model_name(self.series, self.rating_a)


@dataclass
class SimulatedEqualizer:
    """A VANN-Guard with its Smart Monitor on one vehicle bus."""

    spec: EqualizerSpec
    system: ElectricalSystem
    transmit: Transmit
    phase_status: float = 0.0
    phase_battery: float = 0.0
    stage: Stage = field(init=False)
    params: dict[str, Any] = field(init=False)
    profile: int = 0
    jso: bool = False
    onoff_en: bool = False
    commanded_on: bool = True
    ss_msg_on: bool = True
    failed: bool = False
    shutdown: bool = False
    heartbeat_mode: str = "normal"  # "normal", "stuck" (stops alternating), "silent"
    heartbeat_value: int = 0
    # Its CAN receive path has failed: it still transmits but acts on no frame sent to it.
    deaf: bool = False
    dtcs: dict[str, DtcState] = field(init=False)
    _next_status: float = field(init=False, default=math.inf)
    _next_battery: float = field(init=False, default=math.inf)
    _next_dm1: float = field(init=False, default=math.inf)
    _outbox: list[_Outgoing] = field(init=False, default_factory=list)
    _started: bool = field(init=False, default=False)

    def __post_init__(self) -> None:
        self.stage = Stage(rating_a=float(self.spec.rating_a))
        self.system.stages.append(self.stage)
        self.dtcs = {code: DtcState() for code in DTC_ORDER}
        self.params = self._defaults()

    # ----- identity -------------------------------------------------------------------------
    @property
    def sa(self) -> int:
        return self.spec.sa

    @property
    def series(self) -> int:
        return self.spec.series

    @property
    def component_text(self) -> str:
        return f"EQ{self.series}{self.spec.hardware_revision:02d}"

    @property
    def software_text(self) -> str:
        return f"EQ{self.series}{self.spec.software_revision:02d}"

    def _defaults(self) -> dict[str, Any]:
        params: dict[str, Any] = dict(DEFAULTS_9)
        if self.series == 80:
            params.update(DEFAULTS_80)
            cap = self.system.a.capacity_ah
            params["peukert_capacity_ah"] = cap
            params["capacity_ah"] = cap
        return params

    # ----- time -----------------------------------------------------------------------------
    def start(self, t: float) -> None:
        """Power up at `t`: first broadcasts after each unit's own phase."""
        self._next_status = t + self.phase_status
        self._next_battery = t + self.phase_battery if self.series == 80 else math.inf
        self._started = True

    def next_wakeup(self) -> float:
        """Earliest time something is due (a broadcast, a DM1, a fault timer, a BAM packet)."""
        times = [self._next_status, self._next_battery, self._next_dm1]
        if self._outbox:
            times.append(self._outbox[0].due)
        timer = float(self.params["fault_timer_s"])
        for st in self.dtcs.values():
            if st.condition_since is not None and not st.reported:
                times.append(max(st.condition_since + timer, st.last_change + DTC_CHANGE_GUARD_S))
            elif st.condition_since is None and st.reported:
                times.append(st.last_change + DTC_CHANGE_GUARD_S)
        return min(times)

    # ----- power stage ----------------------------------------------------------------------
    def prepare(self) -> None:
        """Decide, from the last readings, whether the power stage may run this step."""
        sol = self.system.solution
        if self.jso:
            # Jump-start override: keep running through the undervoltage shutdown.
            low = min(sol.va, sol.vb) < JSO_MIN_BATTERY_V
        else:
            low = (
                sol.v24 < SHUTDOWN_SYSTEM_V
                or sol.va < SHUTDOWN_BATTERY_V
                or sol.vb < SHUTDOWN_BATTERY_V
            )
        self.shutdown = low
        self.stage.available = self.commanded_on and not self.failed and not low

    @property
    def running(self) -> bool:
        return self.stage.available and self.stage.amps > RUNNING_MIN_A

    # ----- faults and DM1 -------------------------------------------------------------------
    def _conditions(self, sol: Solution) -> dict[str, bool]:
        p = self.params
        prev = {code: st.condition_since is not None for code, st in self.dtcs.items()}
        ov, uv = float(p["ov_setpoint_v"]), float(p["uv_setpoint_v"])
        diff = abs(sol.vb - sol.va)
        # A condition that is already present clears only past a hysteresis band.
        return {
            "OVF": sol.v24 > (ov - HYSTERESIS_V if prev["OVF"] else ov),
            "UVF": sol.v24 < (uv + HYSTERESIS_V if prev["UVF"] else uv),
            "IMB": diff > (IMB_THRESHOLD_V - HYSTERESIS_V / 2 if prev["IMB"] else IMB_THRESHOLD_V),
            "EQFLT": self.failed,
        }

    def _update_dtcs(self, t: float, sol: Solution) -> None:
        timer = float(self.params["fault_timer_s"])
        changed = False
        for code, present in self._conditions(sol).items():
            st = self.dtcs[code]
            if present and st.condition_since is None:
                st.condition_since = t
            elif not present:
                st.condition_since = None
            # The fault timer: a condition must hold this long before the fault is reported.
            want = st.condition_since is not None and t - st.condition_since >= timer - 1e-9
            if want != st.reported and t - st.last_change >= DTC_CHANGE_GUARD_S - 1e-9:
                st.reported = want
                st.last_change = t
                if want:
                    st.occurrences = min(OC_MAX, st.occurrences + 1)
                changed = True
        if changed:
            self._send_dm1(t)
            self._next_dm1 = t + DM1_PERIOD_S if self.active_codes() else math.inf
        elif t >= self._next_dm1 - 1e-9:
            if self.active_codes():
                self._send_dm1(t)
                self._next_dm1 = t + DM1_PERIOD_S
            else:
                self._next_dm1 = math.inf

    def active_codes(self) -> list[str]:
        """Codes DM1 reports as active right now, in DM1 order."""
        return [code for code in DTC_ORDER if self.dtcs[code].reported]

    def dm1_fields(self) -> dict[str, Any]:
        """The DM1 as the unit would send it now (all-clear when nothing is active)."""
        codes = self.active_codes()
        if not codes:
            return {"lamps": {"mil": 0, "rsl": 0, "awl": 0, "pl": 0}, "dtcs": []}
        dtcs = [
            {
                "spn": NAMED_CODES[c][0],
                "fmi": NAMED_CODES[c][1],
                "oc": self.dtcs[c].occurrences,
                "cm": 0,
            }
            for c in codes
        ]
        # 0x08 in the lamp byte, as the manuals' frames show for "Amber Warning Lamp on".
        return {"lamps": {"mil": 0, "rsl": 0, "awl": 2, "pl": 0}, "dtcs": dtcs}

    def _send_dm1(self, t: float) -> None:
        self._queue(t, encode("dm1", self.dm1_fields(), sa=self.sa))

    def _queue(self, t: float, frames: list[Frame]) -> None:
        if len(frames) == 1 and not self._outbox:
            self.transmit(t, *frames[0])
            return
        # Multi-packet transfers are paced; a new one waits for the previous to finish.
        due = max(t, self._outbox[-1].due + BAM_PACKET_GAP_S) if self._outbox else t
        for i, (can_id, data) in enumerate(frames):
            self._outbox.append(_Outgoing(due + i * BAM_PACKET_GAP_S, can_id, data))
        self._flush(t)

    def _flush(self, t: float) -> None:
        while self._outbox and self._outbox[0].due <= t + 1e-9:
            out = self._outbox.pop(0)
            self.transmit(out.due, out.can_id, out.data)

    # ----- broadcasts -----------------------------------------------------------------------
    def status_fields(self) -> dict[str, str]:
        """The 16 status flags, consistent with what DM1 reports."""

        def flag(on: bool) -> str:
            return "active" if on else "inactive"

        d = self.dtcs
        battflt = d["OVF"].reported or d["UVF"].reported or d["IMB"].reported
        return {
            "state_can_jso": flag(self.jso),
            "state_onoff_en": flag(self.onoff_en),
            "ex24f": "inactive",
            "ex12f": "inactive",
            "exgnf": "inactive",
            "ovf": flag(d["OVF"].reported),
            "uvf": flag(d["UVF"].reported),
            "imb": flag(d["IMB"].reported),
            "eqrn": flag(self.running),
            "eqflt": flag(d["EQFLT"].reported),
            "io_in_sdn": flag(self.shutdown),
            "vcfl": "inactive",
            "vcfh": "inactive",
            # 80-series: no Smart Sensor control, the flag keeps its "active by default".
            "can_ss_msg_on": flag(self.ss_msg_on if self.series == 70 else True),
            "eq_state_onoff": flag(self.commanded_on),
            "eq_battflt": flag(battflt) if self.series == 80 else "not_available",
        }

    def voltages_fields(self, sol: Solution) -> dict[str, float | None]:
        """V12, V24 and (80-series) the 12 V and 24 V battery currents, positive charging."""
        fields: dict[str, float | None] = {
            "v12": round(max(0.0, sol.v12), 3),
            "v24": round(max(0.0, sol.v24), 3),
        }
        if self.series == 80:
            fields["i12"] = round(sol.ia, 2)
            fields["i24"] = round(sol.ib, 2)
        return fields

    def _runtime_min(self, discharge_a: float, soc: float, soh: float) -> float:
        p = self.params
        if discharge_a <= abs(float(p["discharge_threshold_a"])):
            return RUNTIME_MAX_MIN  # not discharging: nothing to run out
        hours = max(float(p["c_rating"]), 1.0)
        cap = float(p["peukert_capacity_ah"])
        n = float(p["peukert_exponent"])
        # Peukert: time to empty from full at this current, scaled by what is left.
        full_h: float = hours * math.pow(cap / (discharge_a * hours), n)
        return min(RUNTIME_MAX_MIN, full_h * 60.0 * soc * soh)

    def _temp_factor(self) -> float:
        p = self.params
        t = self.system.temperature_c
        factor = 1.0 + float(p["temp_constant"]) * (t - float(p["rated_temp_c"]))
        return min(1.2, max(0.3, factor))

    @staticmethod
    def _states(current: float, soc: float, p: dict[str, Any]) -> tuple[int, int]:
        # Major: 0 rest, 1 charging, 2 discharging, 3 cranking. Minor: charge stage (bulk,
        # absorption, float) or discharge depth (normal, low, critical). The manuals do not
        # define these codes; they are the simulator's.
        if current <= -float(p["start_threshold_a"]):
            return 3, 0
        if current >= float(p["charge_threshold_a"]):
            return 1, 0 if soc < 0.8 else 1 if soc < 0.98 else 2
        if current <= float(p["discharge_threshold_a"]):
            return 2, 0 if soc >= 0.5 else 1 if soc >= 0.2 else 2
        return 0, 0

    def battery_states_fields(self, sol: Solution) -> list[dict[str, Any]]:
        """Indexes 1-5 of PGN 65497, computed from the batteries' state."""
        a, b = self.system.a, self.system.b
        # The manuals' "12V battery" is the one between ground and +12 V (battery A), the
        # "24V battery" the one between +12 V and +24 V (battery B): each is reported from its
        # own charge and health, as the monitor measures each battery on its own.
        soc12, soh12 = a.soc, a.soh
        soc24, soh24 = b.soc, b.soh
        out: list[dict[str, Any]] = []
        tf = self._temp_factor()
        for first, soc, soh, current in ((1, soc12, soh12, sol.ia), (3, soc24, soh24, sol.ib)):
            run = self._runtime_min(-current, soc, soh)
            run_adj = run if run >= RUNTIME_MAX_MIN else run * tf
            out.append(
                {
                    "index": first,
                    "soc_achievable": round(100.0 * min(1.0, 0.5 + 0.5 * soh), 1),
                    "soh": round(100.0 * soh, 1),
                    "runtime_min": round(run * 2) / 2,
                }
            )
            out.append(
                {
                    "index": first + 1,
                    "runtime_temp_adj_min": round(run_adj * 2) / 2,
                    "dod": round(100.0 * (1.0 - soc), 1),
                    "soc": round(100.0 * soc, 1),
                }
            )
        maj12, min12 = self._states(sol.ia, soc12, self.params)
        maj24, min24 = self._states(sol.ib, soc24, self.params)
        out.append(
            {
                "index": 5,
                "major_12v": maj12,
                "minor_12v": min12,
                "major_24v": maj24,
                "minor_24v": min24,
                "temperature_c": round(self.system.temperature_c, 1),
            }
        )
        return out

    def _broadcast(self, t: float, sol: Solution) -> None:
        if t >= self._next_status - 1e-9:
            self._next_status = next_after(self._next_status, t + 1e-9, STATUS_PERIOD_S)
            self.transmit(t, *encode("status", self.status_fields(), sa=self.sa)[0])
            if self.heartbeat_mode != "silent":
                hb = encode("heartbeat", {"heartbeat": self.heartbeat_value}, sa=self.sa)[0]
                self.transmit(t, *hb)
                if self.heartbeat_mode == "normal":
                    self.heartbeat_value ^= 1
            fields = self.voltages_fields(sol)
            self.transmit(t, *encode("voltages", fields, sa=self.sa, series=self.series)[0])
        if self.series == 80 and t >= self._next_battery - 1e-9:
            self._next_battery = next_after(self._next_battery, t + 1e-9, BATTERY_STATES_PERIOD_S)
            for fields in self.battery_states_fields(sol):
                self.transmit(t, *encode("battery_states", fields, sa=self.sa)[0])

    def update(self, t: float, sol: Solution) -> None:
        """Run the monitor at time `t` on the latest readings."""
        if not self._started:
            self.start(t)
        self._flush(t)
        self._update_dtcs(t, sol)
        self._broadcast(t, sol)

    # ----- frames to the unit ---------------------------------------------------------------
    def handle(self, t: float, record: Record) -> None:
        """React to a decoded control, parameters or request record."""
        if self.deaf:
            return
        if record.name == "request":
            self._on_request(t, record.fields)
        elif record.name == "control":
            self._on_control(record.fields)
        elif record.name == "parameters":
            self._on_parameters(record.fields)

    def _on_request(self, t: float, fields: dict[str, Any]) -> None:
        if fields.get("da") not in (self.sa, GLOBAL_ADDRESS):
            return
        pgn = fields.get("requested_pgn")
        if pgn == PGN_DM1:
            self._send_dm1(t)
        elif pgn == PGN_COMPONENT_ID:
            self._queue(t, encode("component_id", {"text": self.component_text}, sa=self.sa))
        elif pgn == PGN_COMPONENT_ID_70_MISPRINT and self.series == 70:
            # A gateway that follows the 70-series manual asks for 0xFEED: answer in kind.
            frame = encode("component_id", {"text": self.component_text}, sa=self.sa)[0]
            self._queue(t, [(compose_id(PGN_COMPONENT_ID_70_MISPRINT, self.sa), frame[1])])
        elif pgn == PGN_SOFTWARE_ID:
            self._queue(t, encode("software_id", {"text": self.software_text}, sa=self.sa))
        # The manuals list only these three as supported; anything else goes unanswered.

    def _on_control(self, fields: dict[str, Any]) -> None:
        jso = fields.get("can_jso")
        if jso in ("enable", "disable"):
            self.jso = jso == "enable"
        en = fields.get("can_onoff_en")
        if en in ("enable", "disable"):
            self.onoff_en = en == "enable"
            if not self.onoff_en:
                # Without CAN on/off control the unit runs as wired: on.
                self.commanded_on = True
        onoff = fields.get("can_eq_onoff")
        if onoff in ("enable", "disable") and self.onoff_en:
            self.commanded_on = onoff == "enable"
        ss = fields.get("can_ss_msg_en")
        if ss in ("enable", "disable") and self.series == 70:
            self.ss_msg_on = ss == "enable"

    def _on_parameters(self, fields: dict[str, Any]) -> None:
        index = fields.get("index")
        allowed = SERIES_80_INDEXES if self.series == 80 else SERIES_70_INDEXES
        if index not in allowed:
            return  # the series does not support it: ignored, as a unit would
        if index == 0:
            self.params = self._defaults()
            profile = fields.get("profile")
            # 0xFF00.. (None) is "not requested, leave unchanged", like every parameter value;
            # out of the manuals' 0..4 is ignored.
            if self.series == 80 and isinstance(profile, int | float) and 0 <= profile <= 4:
                self.profile = int(profile)
            return
        for name, value in fields.items():
            if name in ("index", "out_of_range") or value is None:
                continue  # None is "not requested, leave unchanged"
            if index == 9 and not _in_range_9(name, float(value)):
                continue
            self.params[name] = value


def _in_range_9(name: str, value: float) -> bool:
    if name in ("ov_setpoint_v", "uv_setpoint_v"):
        return 20.0 <= value <= 40.0
    if name == "fault_timer_s":
        return 0 <= value <= 60
    return True
