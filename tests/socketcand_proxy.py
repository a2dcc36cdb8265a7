"""A TCP proxy in front of a socketcand server that counts the buses opening: connections
that sent their `< open NAME >` and were not yet answered `< ok >` (nor closed). The count
goes up after a client asked and down before the client can see its answer, so it never
counts more than the client side had opening. Its own event loop runs in a thread;
`max_opening` is the most seen at once, `opened` the opens answered."""

from __future__ import annotations

import asyncio
import contextlib
import threading
from typing import Any


class OpeningCounter:
    def __init__(self, upstream: tuple[str, int]) -> None:
        self.upstream = upstream
        self.opening = 0
        self.max_opening = 0
        self.opened = 0
        self.port = 0
        self._lock = threading.Lock()
        self._loop = asyncio.new_event_loop()
        self._ready = threading.Event()
        self._server: asyncio.Server | None = None
        self._thread = threading.Thread(target=self._run, name="socketcand proxy", daemon=True)

    def start(self) -> OpeningCounter:
        self._thread.start()
        assert self._ready.wait(10), "the proxy did not start"
        return self

    def stop(self) -> None:
        self._loop.call_soon_threadsafe(self._loop.stop)
        self._thread.join(10)

    def _run(self) -> None:
        asyncio.set_event_loop(self._loop)
        self._server = self._loop.run_until_complete(
            asyncio.start_server(self._client, "127.0.0.1", 0)  # backlog 100, as the server's
        )
        self.port = self._server.sockets[0].getsockname()[1]
        self._ready.set()
        self._loop.run_forever()
        self._server.close()
        for task in asyncio.all_tasks(self._loop):
            task.cancel()
        with contextlib.suppress(Exception):
            self._loop.run_until_complete(asyncio.sleep(0))
        self._loop.close()

    def _count(self, delta: int) -> None:
        with self._lock:
            self.opening += delta
            self.max_opening = max(self.max_opening, self.opening)

    async def _client(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        state = {"asked": False, "answered": False}

        def done_opening() -> None:
            if state["asked"] and not state["answered"]:
                state["answered"] = True
                self._count(-1)

        try:
            up_reader, up_writer = await asyncio.open_connection(*self.upstream)
        except OSError:
            writer.close()
            return

        async def pipe(src: asyncio.StreamReader, dst: asyncio.StreamWriter, up: bool) -> None:
            seen = b""
            try:
                while data := await src.read(65536):
                    if not state["answered"]:
                        seen = (seen + data)[-4096:]
                        if up and not state["asked"] and b"< open " in seen:
                            state["asked"] = True
                            self._count(+1)
                        elif not up and state["asked"] and b"< ok >" in seen:
                            with self._lock:
                                self.opened += 1
                            done_opening()
                    dst.write(data)
                    await dst.drain()
            except (OSError, asyncio.IncompleteReadError):
                pass
            finally:
                with contextlib.suppress(Exception):
                    dst.close()

        tasks: list[Any] = [
            asyncio.create_task(pipe(reader, up_writer, True)),
            asyncio.create_task(pipe(up_reader, writer, False)),
        ]
        try:
            await asyncio.wait(tasks, return_when=asyncio.FIRST_COMPLETED)
        finally:
            for t in tasks:
                t.cancel()
            done_opening()
            for w in (writer, up_writer):
                with contextlib.suppress(Exception):
                    w.close()
