"""Benchmark: what the gateway's J1939 network management costs, on a python-can virtual bus.

For each round a BusReader is opened as `eqgw serve` opens a bus (address claim on by default)
and, from a plain python-can endpoint on the same channel, the script measures:

- claim: from the claim frame on the wire to the first request the gateway sends (J1939-81
  makes it wait 250 ms for an address in 128..247; this is that wait plus scheduling);
- nack: from a destination-specific request to the gateway's NACK;
- cts: from an RTS for a DM1 to the gateway's CTS.

    python -m bench.j1939_node --rounds 20

Prints the median, min and max of each in milliseconds.
"""

from __future__ import annotations

import argparse
import asyncio
import statistics
import time
import uuid

import can

from eqgw.bus.reader import BusReader
from eqgw.bus.writer import BusWriter
from eqgw.config import Settings


async def _recv(bus: can.BusABC, pf: int, timeout: float = 5.0) -> can.Message:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        msg = bus.recv(0)
        if msg is None:
            await asyncio.sleep(0.0005)
        elif (msg.arbitration_id >> 16) & 0xFF == pf and msg.arbitration_id & 0xFF == 0xD8:
            return msg
    raise TimeoutError(f"no frame with PF 0x{pf:02X} from the gateway")


async def one_round() -> tuple[float, float, float]:
    channel = f"bench-{uuid.uuid4().hex[:8]}"
    settings = Settings(
        vehicles=[{"id": "V"}],
        buses=[{"name": "V/can0", "vehicle_id": "V", "interface": "virtual", "channel": channel}],
    )
    other = can.Bus(interface="virtual", channel=channel)
    try:
        async with BusReader(settings.buses[0]) as reader:
            await reader.wait_open(10)
            await BusWriter(reader).send(0x18EA1ED8, b"\xca\xfe\x00")
            claim = await _recv(other, 0xEE)
            request = await _recv(other, 0xEA)
            claim_ms = (request.timestamp - claim.timestamp) * 1000
            sent = time.time()
            other.send(can.Message(arbitration_id=0x18EAD880, data=b"\xeb\xfe\x00"))
            nack = await _recv(other, 0xE8)
            nack_ms = (nack.timestamp - sent) * 1000
            rts = bytes([0x10, 14, 0, 2, 0xFF, 0xCA, 0xFE, 0x00])
            sent = time.time()
            other.send(can.Message(arbitration_id=0x1CECD81E, data=rts))
            cts = await _recv(other, 0xEC)
            cts_ms = (cts.timestamp - sent) * 1000
            return claim_ms, nack_ms, cts_ms
    finally:
        other.shutdown()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=20)
    args = parser.parse_args()
    results = [asyncio.run(one_round()) for _ in range(args.rounds)]
    for i, what in enumerate(("claim -> first request", "request -> NACK", "RTS -> CTS")):
        values = [r[i] for r in results]
        print(
            f"{what}: median {statistics.median(values):.1f} ms, "
            f"min {min(values):.1f} ms, max {max(values):.1f} ms ({args.rounds} rounds)"
        )


if __name__ == "__main__":
    main()
