"""`eqgw forward`: run on a vehicle, buffer its equalizer frames, upload them when online."""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import os
import signal
import sqlite3
import sys
import time
from typing import Any

from eqgw.describe import describe
from eqgw.supervisor import FatalError

DEFAULT_BUFFER = "eqgw-forward.db"


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """Add `eqgw forward` to the command line."""
    p = subparsers.add_parser(
        "forward",
        help="edge mode: buffer a vehicle bus locally and upload it to a central eqgw",
        description=(
            "Read one vehicle bus, keep its equalizer frames (or all frames) in a local SQLite "
            "buffer and upload them in batches whenever the central service answers. Frames "
            "leave the buffer only once the central service has stored them; a restart resumes "
            "where the last acknowledgement left off."
        ),
    )
    p.add_argument(
        "--bus",
        required=True,
        metavar="INTERFACE:CHANNEL",
        help="python-can interface and channel, e.g. socketcan:can0 or socketcand:SIM-001",
    )
    p.add_argument(
        "--option",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="extra can.Bus argument (host=10.1.2.3, port=29536); integers are converted",
    )
    p.add_argument("--bitrate", type=int, default=250_000, help="bitrate (default 250000)")
    p.add_argument(
        "--sa", default="30", help="equalizer source addresses, comma-separated (default 30)"
    )
    p.add_argument("--vehicle", required=True, help="the vehicle id, as configured centrally")
    p.add_argument(
        "--bus-name", help="bus name the central service files units under (VEHICLE/CHANNEL)"
    )
    p.add_argument("--to", required=True, metavar="URL", help="central API, .../api/v1")
    p.add_argument(
        "--key",
        default=os.environ.get("EQGW_FORWARD_KEY"),
        help="an ingest key (default: EQGW_FORWARD_KEY; the environment keeps it out of ps)",
    )
    p.add_argument("--buffer", default=DEFAULT_BUFFER, help=f"buffer file ({DEFAULT_BUFFER})")
    p.add_argument("--max-rows", type=int, default=5_000_000, help="buffer bound in frames")
    p.add_argument("--max-mb", type=float, default=1024.0, help="buffer bound in MB (1024)")
    p.add_argument(
        "--all-frames", action="store_true", help="keep every frame, not only the equalizers'"
    )
    p.add_argument("--batch-frames", type=int, default=2000, help="frames per upload (2000)")
    p.add_argument("--no-gzip", action="store_true", help="upload uncompressed JSON")
    p.add_argument(
        "--backoff-max", type=float, default=30.0, help="longest wait between retries (30 s)"
    )
    p.add_argument(
        "--status-every", type=float, default=60.0, help="print a status line this often (s)"
    )
    p.set_defaults(func=run)


def _options(values: list[str]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for item in values:
        key, sep, value = item.partition("=")
        if not sep or not key:
            raise ValueError(f"--option wants KEY=VALUE, got {item!r}")
        out[key] = int(value) if value.lstrip("-").isdigit() else value
    return out


def _say(text: str) -> None:
    sys.stdout.write(f"eqgw forward: {text}\n")
    sys.stdout.flush()


def run(args: argparse.Namespace) -> int:
    """Entry point of `eqgw forward`."""
    from eqgw.bus.config import BusConfig
    from eqgw.forward.buffer import FrameBuffer
    from eqgw.forward.protocol import default_bus_name
    from eqgw.forward.uploader import Forwarder, UploadSettings

    if not args.key:
        print("eqgw forward: give --key or set EQGW_FORWARD_KEY", file=sys.stderr)
        return 2
    interface, sep, channel = args.bus.partition(":")
    try:
        if not sep or not interface or not channel:
            raise ValueError(f"--bus wants INTERFACE:CHANNEL, got {args.bus!r}")
        sas = [int(x, 0) for x in args.sa.split(",") if x.strip()]
        name = args.bus_name or default_bus_name(args.vehicle, channel)
        bus = BusConfig(
            name=name,
            vehicle_id=args.vehicle,
            interface=interface,
            channel=channel,
            bitrate=args.bitrate,
            options=_options(args.option),
            equalizer_sas=sas,
        )
    except ValueError as exc:
        print(f"eqgw forward: {exc}", file=sys.stderr)
        return 2
    try:
        buffer = FrameBuffer(
            args.buffer, max_rows=args.max_rows, max_bytes=int(args.max_mb * 1024 * 1024)
        )
    except ValueError as exc:
        print(f"eqgw forward: {exc}", file=sys.stderr)
        return 2
    except (sqlite3.Error, OSError) as exc:
        # A damaged, read-only or unreachable buffer file: no retry will open it.
        print(
            f"eqgw forward: the buffer {args.buffer} cannot be used: {describe(exc)}",
            file=sys.stderr,
        )
        return 1
    upload = UploadSettings(
        url=args.to,
        key=args.key,
        vehicle=args.vehicle,
        bus=name,
        equalizer_sas=tuple(sas),
        batch_frames=args.batch_frames,
        gzip=not args.no_gzip,
        backoff_max_s=max(args.backoff_max, 0.5),
    )
    fatal: list[FatalError] = []
    fwd = Forwarder(bus, buffer, upload, all_frames=args.all_frames, on_fatal=fatal.append)
    try:
        asyncio.run(_serve(fwd, args.status_every, fatal))
    finally:
        buffer.close()
    if fatal:
        # One line, a non-zero exit: systemd or Docker restart it, an operator reads why.
        print(f"eqgw forward: {fatal[0]}", file=sys.stderr)
        return 1
    return 0


def _status_line(s: dict[str, Any]) -> str:
    b, u = s["buffer"], s["upload"]
    line = (
        f"read {s['frames_read']}, kept {s['frames_kept']}, buffered {b['rows']}, "
        f"acked up to {b['acked_seq']}, dropped {s['dropped']}, upload {u['state']}"
        + (f" ({u['last_error']})" if u["last_error"] else "")
    )
    if u["frames_refused"]:
        line += f"; {u['frames_refused']} refused by the central for their time (check the clock)"
    for name, t in s["tasks"].items():
        if t["state"] not in ("running", "done"):
            line += f"; {name} {t['state']} after {t['failures']} failures ({t['last_error']})"
    return line


async def _serve(fwd: Any, status_every: float, fatal: list[FatalError]) -> None:
    st = fwd.buffer.status()
    _say(
        f"buffer {fwd.buffer.path} (stream {st.stream}): {st.rows} frames waiting, "
        f"{st.dropped} dropped so far; bus {fwd.bus.name} -> {fwd.uploader.settings.url}"
    )
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        with contextlib.suppress(NotImplementedError):
            loop.add_signal_handler(sig, stop.set)
    await fwd.start()
    said_open = False
    last_status = time.monotonic()
    try:
        while not stop.is_set() and not fatal:
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout(0.2):
                    await stop.wait()
            if not said_open and fwd.reader.state == "open":
                said_open = True
                _say("bus open")
            if time.monotonic() - last_status >= status_every:
                last_status = time.monotonic()
                _say(_status_line(fwd.status()))
    finally:
        await fwd.stop()
        st = fwd.buffer.status()
        _say(f"stopped: {st.rows} frames still buffered (uploaded at the next start)")
