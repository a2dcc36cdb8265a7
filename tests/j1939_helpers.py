"""Helpers of the tests that put an independent J1939 stack (can-j1939) on a virtual bus."""

from __future__ import annotations

import can
import j1939


class Observer:
    """Every frame on the bus, with the time it was seen (a plain python-can endpoint)."""

    def __init__(self, channel: str) -> None:
        self.bus = can.Bus(interface="virtual", channel=channel)
        self.seen: list[can.Message] = []

    def drain(self) -> list[can.Message]:
        while (msg := self.bus.recv(0)) is not None:
            self.seen.append(msg)
        return self.seen

    def frames(self, *, sa: int | None = None, pf: int | None = None) -> list[can.Message]:
        return [
            m
            for m in self.drain()
            if (sa is None or m.arbitration_id & 0xFF == sa)
            and (pf is None or (m.arbitration_id >> 16) & 0xFF == pf)
        ]


def stack_name(industry_group: int, function: int, identity: int) -> j1939.Name:
    return j1939.Name(
        arbitrary_address_capable=0,
        industry_group=industry_group,
        vehicle_system_instance=0,
        vehicle_system=0,
        function=function,
        function_instance=0,
        ecu_instance=0,
        manufacturer_code=0,
        identity_number=identity,
    )
