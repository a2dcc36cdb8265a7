"""`eqgw forward` on a full disk: its buffer lives on a small filesystem (a tmpfs) that fills
up while the central service is away. The reading loop fails, is retried with backoff and said
in the status line; the frames it could not keep are counted as dropped; once space is freed
it keeps frames again, in the same process. A vehicle simulated over socketcand."""

from __future__ import annotations

import asyncio
import contextlib
import re
import uuid
from collections.abc import Iterator
from pathlib import Path

from eqgw.bus.socketcand_server import SocketcandServer
from tests.forward_helpers import VEHICLE, RecordedVehicle, async_wait
from tests.proc_helpers import Process, eqgw, free_port, mounted

STATUS = re.compile(r"read (\d+), kept (\d+), buffered \d+, acked up to \d+, dropped (\d+)")


@contextlib.contextmanager
def small_filesystem(tmp_path: Path, size: str) -> Iterator[Path]:
    """A tmpfs of `size` mounted in tmp_path (root only; skipped elsewhere)."""
    mnt = tmp_path / f"small-{uuid.uuid4().hex[:6]}"
    mnt.mkdir()
    tmpfs = ["-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(mnt)]
    with mounted(mnt, tmpfs, what="a tmpfs") as path:
        yield path


def _fill(mnt: Path, leave: int) -> Path:
    """Fill the filesystem but `leave` bytes; the filler file is returned (delete to free)."""
    filler = mnt / "filler"
    with filler.open("wb") as f:
        with contextlib.suppress(OSError):
            while True:
                f.write(b"\0" * 65536)
                f.flush()
    import os

    free = os.statvfs(mnt).f_bavail * os.statvfs(mnt).f_frsize
    size = filler.stat().st_size
    with filler.open("r+b") as f:
        f.truncate(max(0, size - max(0, leave - free)))
    return filler


def _last_status(proc: Process) -> tuple[int, int, int] | None:
    found = [STATUS.search(line) for line in list(proc.lines)]
    hits = [m for m in found if m]
    if not hits:
        return None
    read, kept, dropped = (int(g) for g in hits[-1].groups())
    return read, kept, dropped


async def test_full_disk_is_retried_counted_and_resumed(tmp_path: Path) -> None:
    veh = RecordedVehicle(seed=3)
    server = SocketcandServer("127.0.0.1", 0, {VEHICLE: veh.channel})
    with small_filesystem(tmp_path, "2m") as mnt:
        await server.start()
        argv = eqgw(
            "forward",
            "--bus", f"socketcand:{VEHICLE}",
            "--option", "host=127.0.0.1",
            "--option", f"port={server.port}",
            "--sa", ",".join(str(sa) for sa in veh.sas),
            "--vehicle", VEHICLE,
            "--bus-name", VEHICLE,
            "--to", f"http://127.0.0.1:{free_port()}/api/v1",  # nobody there: frames stay
            "--buffer", str(mnt / "fwd.db"),
            "--all-frames",
            "--backoff-max", "0.5",
            "--status-every", "0.3",
        )  # fmt: skip
        fwd = Process(argv, tmp_path, {"EQGW_FORWARD_KEY": "k" * 32})
        try:
            await async_wait(lambda: "bus open" in fwd.output(), 60, "the forwarder's bus")
            await asyncio.sleep(0.5)
            filler = await asyncio.to_thread(_fill, mnt, 96 * 1024)
            veh.fleet.open()

            async def drive_until(cond: object, what: str) -> None:
                for _ in range(400):
                    veh.fleet.advance(5.0)
                    await asyncio.sleep(0.05)
                    if cond():  # type: ignore[operator]
                        return
                raise AssertionError(f"never: {what}\n{fwd.output()[-3000:]}")

            await drive_until(lambda: "read backoff" in fwd.output(), "the disk full")
            assert "database or disk is full" in fwd.output()
            for _ in range(40):  # full for a while: retried, and the process stays up
                veh.fleet.advance(5.0)
                await asyncio.sleep(0.05)
            assert fwd.proc.poll() is None
            assert fwd.output().count("database or disk is full") >= 2
            at_full = _last_status(fwd)
            assert at_full is not None
            filler.unlink()  # space is back

            def keeps_again() -> bool:
                now = _last_status(fwd)
                return now is not None and now[1] > at_full[1] + 100

            await drive_until(keeps_again, "frames kept again after space was freed")
            assert fwd.proc.poll() is None
            veh.fleet.close()
            await asyncio.sleep(1.0)  # the last frames read and a status line said
            assert await asyncio.to_thread(fwd.stop) == 0
        finally:
            await asyncio.to_thread(fwd.stop)
            await server.stop()
            with contextlib.suppress(Exception):
                veh.fleet.close()
        final = _last_status(fwd)
        assert final is not None
        read, kept, dropped = final
        assert dropped > 0, "frames read while the disk was full are counted as dropped"
        assert kept + dropped == read  # every frame read is kept or counted
        assert "stopped:" in fwd.output()
