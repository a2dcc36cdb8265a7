"""Other J1939 nodes a vehicle bus carries, so a gateway sees realistic mixed traffic."""

from __future__ import annotations

import math
import random
from collections.abc import Callable
from dataclasses import dataclass

from eqgw.protocol.j1939 import compose_id
from eqgw.sim.clock import next_after

ENGINE_SA = 0x00
TRANSMISSION_SA = 0x03
# Another vendor's device using the same proprietary PGN range the equalizer uses (SPEC-NOTES:
# such frames must not be decoded as equalizer data).
OTHER_VENDOR_SA = 0x90

PGN_EEC1 = 0xF004  # 61444 electronic engine controller 1 (engine speed)
PGN_ETC1 = 0xF002  # 61442 electronic transmission controller 1
PGN_CCVS = 0xFEF1  # 65265 cruise control / vehicle speed
PGN_ET1 = 0xFEEE  # 65262 engine temperature 1
PGN_VEP1 = 0xFEF7  # 65271 vehicle electrical power 1 (battery potential)
PGN_OTHER_VENDOR = 0xFFD4


@dataclass(slots=True)
class _Periodic:
    pgn: int
    sa: int
    period_s: float
    next_s: float
    priority: int


class BackgroundTraffic:
    """Engine, transmission and a foreign proprietary device broadcasting on one bus."""

    def __init__(
        self,
        rng: random.Random,
        engine_running: Callable[[], bool],
        battery_volts: Callable[[], float],
    ) -> None:
        self._rng = rng
        self._engine_running = engine_running
        self._battery_volts = battery_volts
        self._nodes = [
            _Periodic(PGN_EEC1, ENGINE_SA, 0.1, 0.0, 3),
            _Periodic(PGN_ETC1, TRANSMISSION_SA, 0.1, 0.0, 3),
            _Periodic(PGN_CCVS, ENGINE_SA, 0.1, 0.0, 6),
            _Periodic(PGN_ET1, ENGINE_SA, 1.0, 0.0, 6),
            _Periodic(PGN_VEP1, ENGINE_SA, 1.0, 0.0, 6),
            _Periodic(PGN_OTHER_VENDOR, OTHER_VENDOR_SA, 1.0, 0.0, 6),
        ]
        self._rpm = 0.0
        self._speed_kmh = 0.0

    def start(self, t: float) -> None:
        """First frames at random phases so vehicles do not burst in step."""
        for node in self._nodes:
            node.next_s = t + self._rng.uniform(0, node.period_s)

    def next_wakeup(self) -> float:
        return min((n.next_s for n in self._nodes), default=math.inf)

    def update(self, t: float, transmit: Callable[[float, int, bytes], None]) -> None:
        """Send every frame that is due at `t`."""
        running = self._engine_running()
        target_rpm = 650.0 + (900.0 if self._speed_kmh > 5 else 0.0) if running else 0.0
        for node in self._nodes:
            if node.next_s > t + 1e-9:
                continue
            node.next_s = next_after(node.next_s, t + 1e-9, node.period_s)
            if node.pgn == PGN_EEC1:
                self._rpm += (target_rpm - self._rpm) * 0.2 + self._rng.uniform(-5, 5) * running
                data = self._eec1(max(0.0, self._rpm))
            elif node.pgn == PGN_ETC1:
                data = bytes([0xFF, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF])
            elif node.pgn == PGN_CCVS:
                if running:
                    self._speed_kmh = min(90.0, max(0.0, self._speed_kmh + self._rng.gauss(0, 1)))
                else:
                    self._speed_kmh = 0.0
                raw = int(self._speed_kmh * 256)
                data = bytes([0xFF, raw & 0xFF, raw >> 8, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF])
            elif node.pgn == PGN_ET1:
                coolant = (85 if running else 25) + 40  # 1 degC/bit, -40 offset
                data = bytes([coolant, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF])
            elif node.pgn == PGN_VEP1:
                raw = min(0xFAFF, int(self._battery_volts() / 0.05))
                data = bytes([0xFF, 0xFF, 0xFF, 0xFF, raw & 0xFF, raw >> 8, 0xFF, 0xFF])
            else:
                data = bytes(self._rng.getrandbits(8) for _ in range(8))
            transmit(t, compose_id(node.pgn, node.sa, priority=node.priority), data)

    @staticmethod
    def _eec1(rpm: float) -> bytes:
        raw = min(0xFAFF, int(rpm / 0.125))
        return bytes([0xF0, 0x7D, 0x7D, raw & 0xFF, raw >> 8, 0xFF, 0xF0, 0x7D])
