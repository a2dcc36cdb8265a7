"""A socketcand link that stops draining: a server that keeps its TCP connection open but stops
reading (and sending), as a frozen process does. The reader stops handing it frames once
nothing has arrived for `stall_after_s`, reports the bus stalled, and resumes when it drains."""

from __future__ import annotations

import asyncio
import contextlib

import can
import pytest

from eqgw.bus.config import BusConfig
from eqgw.bus.errors import BusStalledError
from eqgw.bus.reader import BusReader
from eqgw.bus.socketcand_server import format_frame
from tests.bus_helpers import TIMEOUT, wait_for, within


class FreezableServer:
    """A socketcand server speaking just enough of the protocol for python-can's client, that
    can be frozen: it then neither reads what it is sent nor sends frames, its socket open."""

    def __init__(self) -> None:
        self.thawed = asyncio.Event()
        self.thawed.set()
        self.received = b""
        self.port = 0
        self._server: asyncio.Server | None = None
        self._tasks: set[asyncio.Task[None]] = set()

    async def __aenter__(self) -> FreezableServer:
        self._server = await asyncio.start_server(self._client, "127.0.0.1", 0)
        self.port = self._server.sockets[0].getsockname()[1]
        return self

    async def __aexit__(self, *exc: object) -> None:
        assert self._server is not None
        self._server.close()
        for task in list(self._tasks):
            task.cancel()
        await asyncio.gather(*self._tasks, return_exceptions=True)
        await self._server.wait_closed()

    async def _client(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        task = asyncio.current_task()
        assert task is not None
        self._tasks.add(task)
        try:
            writer.write(b"< hi >")
            await reader.readuntil(b">")  # < open NAME >
            writer.write(b"< ok >")
            await reader.readuntil(b">")  # < rawmode >
            writer.write(b"< ok >")
            await writer.drain()
            await asyncio.sleep(0.1)  # python-can reads the `< ok >` alone
            feeder = asyncio.create_task(self._feed(writer))
            self._tasks.add(feeder)
            while True:
                await self.thawed.wait()
                data = await reader.read(4096)
                if not data:
                    return
                if self.thawed.is_set():
                    self.received += data
                else:  # froze while waiting: a frozen process would read it only on thaw
                    await self.thawed.wait()
                    self.received += data
        except (ConnectionError, asyncio.IncompleteReadError):
            return
        finally:
            writer.close()
            with contextlib.suppress(ConnectionError):
                await writer.wait_closed()

    async def _feed(self, writer: asyncio.StreamWriter) -> None:
        """A unit's traffic, 5 frames a second, while thawed."""
        i = 0
        while True:
            await self.thawed.wait()
            msg = can.Message(arbitration_id=0x18FEF11E, data=i.to_bytes(8, "little"))
            line = format_frame(msg)
            assert line is not None
            writer.write(line.encode())
            await writer.drain()
            i += 1
            await asyncio.sleep(0.2)

    def sends(self) -> int:
        return self.received.count(b"< send ")


@pytest.mark.timeout(120)
async def test_a_link_that_stops_draining_is_not_fed_and_recovers() -> None:
    async with FreezableServer() as server:
        config = BusConfig(
            name="BUS-101/can0",
            vehicle_id="BUS-101",
            interface="socketcand",
            channel="BUS-101",
            options={"host": "127.0.0.1", "port": server.port},
            stall_after_s=1.0,
        )
        msg = can.Message(arbitration_id=0x18FFD2D8, data=bytes(8))
        async with BusReader(config) as reader:
            await reader.wait_open(TIMEOUT)
            await within(reader.get(), TIMEOUT)  # traffic flows
            await reader.send_message(msg)
            await wait_for(lambda: server.sends() == 1, "the first frame at the server")

            server.thawed.clear()  # frozen, its socket open
            handed = 0
            with pytest.raises(BusStalledError, match="link stalled"):
                for _ in range(200):  # 1 frame each 0.1 s: stalled after about 1 s
                    await reader.send_message(msg)
                    handed += 1
                    await asyncio.sleep(0.1)
            status = reader.status()
            assert status.stalled and status.state == "open"
            assert status.last_error is not None and "link stalled" in status.last_error
            assert 1 <= handed < 200
            # Held back, not lost: nothing of it reached the frozen server yet.
            assert server.sends() == 1
            with pytest.raises(BusStalledError):
                await reader.send_message(msg)  # and it stays refused while frozen

            server.thawed.set()
            await wait_for(lambda: not reader.status().stalled, "the link to drain again")
            # What was handed over arrives on the thaw, late: exactly that, nothing refused.
            await wait_for(lambda: server.sends() == 1 + handed, "the held frames")
            assert reader.status().frames_handed == 1 + handed
            await reader.send_message(msg)
            await wait_for(lambda: server.sends() == 2 + handed, "a frame after the thaw")
