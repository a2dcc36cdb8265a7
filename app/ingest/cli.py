"""`eqgw replay`, `eqgw export` and `eqgw db ...`: load logs into the history, write the raw
archive out as a log, migrate, prune."""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Iterator
from typing import TYPE_CHECKING

from eqgw.protocol.cli import SALVAGED_EXIT, parse_sas

if TYPE_CHECKING:
    from sqlalchemy import Engine

    from eqgw.config import Settings
    from eqgw.store.archive import Frame


def _settings(args: argparse.Namespace) -> Settings | None:
    from eqgw.config import ConfigError, load_settings

    overrides: dict[str, str] = {}
    if getattr(args, "db", None):
        overrides["database_url"] = args.db
    try:
        return load_settings(args.config, **overrides)
    except ConfigError as exc:
        print(f"eqgw: {exc}", file=sys.stderr)
        return None


def _replay(args: argparse.Namespace) -> int:
    from eqgw.ingest.replay import ReplayError, replay_file
    from eqgw.store.errors import StoreError

    settings = _settings(args)
    if settings is None:
        return 2
    from eqgw.fleet.registry import in_effect

    settings = in_effect(settings)  # the database's vehicles and buses, once it has them
    if args.no_raw:
        settings = settings.model_copy(update={"raw_archive": False})
    try:
        summary = replay_file(
            args.file,
            args.vehicle,
            settings,
            progress=not args.quiet and sys.stderr.isatty(),
            sas=args.sa,
        )
    except ReplayError as exc:
        print(f"eqgw replay: {exc}", file=sys.stderr)
        return exc.exit_code
    except StoreError as exc:
        print(f"eqgw replay: {exc}", file=sys.stderr)
        return 1
    if args.json:
        print(json.dumps(summary.as_dict(), default=str))
    else:
        print(summary.text())
    if summary.writer.pending_rows or summary.read_error is not None:
        return 1
    if summary.truncated is not None:
        # As `eqgw decode` says it: 3 when frames before the cut were stored, else 2.
        print(f"eqgw replay: {summary.path}: {summary.truncated}", file=sys.stderr)
        return SALVAGED_EXIT if summary.frames else 2
    return 0


def _export(args: argparse.Namespace) -> int:
    import time

    from sqlalchemy.exc import SQLAlchemyError

    from eqgw.bus.export import FORMATS, format_of
    from eqgw.describe import describe
    from eqgw.store.engine import create_engine
    from eqgw.store.errors import StoreError

    settings = _settings(args)
    if settings is None:
        return 2
    fmt = args.format or format_of(args.out)
    if fmt is None:
        print(
            f"eqgw export: give --format (one of {', '.join(FORMATS)}) or an --out file ending "
            f"in {', '.join(FORMATS.values())}",
            file=sys.stderr,
        )
        return 2
    try:
        end = _time(args.to, time.time(), "--to")
        start = _time(args.from_, end - 3600.0, "--from")
    except ValueError as exc:
        print(f"eqgw export: {exc}", file=sys.stderr)
        return 2
    if not start < end:
        print("eqgw export: --from must be before --to", file=sys.stderr)
        return 2
    engine = create_engine(settings.database_url, deadlines=settings.db)
    try:
        return _write_export(args, engine, fmt, start, end)
    except (SQLAlchemyError, StoreError) as exc:
        print(f"eqgw export: the database cannot be read: {describe(exc)}", file=sys.stderr)
        return 1
    finally:
        engine.dispose()


def _write_export(
    args: argparse.Namespace, engine: Engine, fmt: str, start: float, end: float
) -> int:
    """The export itself (the archive read a page at a time, written as read)."""
    from sqlalchemy import select

    from eqgw.bus.export import ExportError, LogExport, export_chunks
    from eqgw.store import archive
    from eqgw.store.models import Unit, table_of

    u = table_of(Unit).c
    with engine.connect() as conn:
        units = [
            dict(r._mapping)
            for r in conn.execute(
                select(u.id, u.bus, u.sa).where(u.vehicle_id == args.vehicle).order_by(u.id)
            )
        ]
    if not units:
        print(f"eqgw export: no vehicle {args.vehicle!r} in the database", file=sys.stderr)
        return 1
    buses = sorted({x["bus"] for x in units})
    channels = {x["id"]: buses.index(x["bus"]) for x in units}
    unit_ids = sorted(channels)

    def pages() -> Iterator[list[tuple[int, Frame]]]:
        cursor: float | None = start
        while cursor is not None:
            with engine.connect() as conn:
                frames, cursor = archive.read_page(conn, unit_ids, cursor, end)
            yield [(channels[uid], f) for uid, f in frames]

    try:
        export = LogExport(fmt)
    except ExportError as exc:
        print(f"eqgw export: {exc}", file=sys.stderr)
        return 2
    with open(args.out, "wb") as out:
        for chunk in export_chunks(pages(), export):
            out.write(chunk)
    print(
        f"{export.frames} frames of {args.vehicle} written to {args.out} ({fmt}); channels: "
        + ", ".join(f"{i} = {bus}" for i, bus in enumerate(buses))
    )
    return 0


def _time(value: str | None, default: float, name: str) -> float:
    """Epoch seconds or ISO 8601 (naive = UTC), as the API takes them."""
    import math
    from datetime import UTC, datetime

    if value is None:
        return default
    try:
        t = float(value)
    except ValueError:
        try:
            dt = datetime.fromisoformat(value.replace("Z", "+00:00"))
        except ValueError:
            raise ValueError(f"{name} {value!r} is neither epoch seconds nor ISO 8601") from None
        return (dt if dt.tzinfo else dt.replace(tzinfo=UTC)).timestamp()
    if not math.isfinite(t):
        raise ValueError(f"{name} {value!r} is not a finite time")
    return t


def _db_upgrade(args: argparse.Namespace) -> int:
    from eqgw.store.errors import StoreError
    from eqgw.store.migrate import upgrade

    settings = _settings(args)
    if settings is None:
        return 2
    try:
        upgrade(settings.database_url, args.revision)
    except StoreError as exc:
        print(f"eqgw db upgrade: {exc}", file=sys.stderr)
        return 1
    print(f"database at {args.revision}: {_safe_url(settings.database_url)}")
    return 0


def _db_prune(args: argparse.Namespace) -> int:
    from eqgw.store.engine import create_engine
    from eqgw.store.partitions import maintain
    from eqgw.store.retention import prune

    settings = _settings(args)
    if settings is None:
        return 2
    r = settings.retention
    engine = create_engine(settings.database_url, deadlines=settings.db)
    try:
        # Partitions first (PostgreSQL): rows a replay put in a default partition move out.
        maintain(
            engine,
            raw_days=r.raw_days,
            rollup_days=r.rollup_days_by_width(),
            ahead_days=r.partitions_ahead_days,
        )
        result = prune(
            engine,
            raw_days=r.raw_days,
            rollup_days=r.rollup_days,
            rollup_days_by_width=r.rollup_days_by_width(),
            batch_rows=r.batch_rows,
        )
    finally:
        engine.dispose()
    dropped = sum(len(v) for v in result.dropped.values())
    print(
        f"deleted {result.total} rows in {result.batches} batches"
        + (f" ({dropped} time partitions dropped)" if dropped else "")
        + f": {result.deleted}"
    )
    return 0


def _db_compact(args: argparse.Namespace) -> int:
    from eqgw.store import archive, packed
    from eqgw.store.engine import create_engine

    settings = _settings(args)
    if settings is None:
        return 2
    engine = create_engine(settings.database_url, deadlines=settings.db)
    try:
        frames = archive.compact(engine)
        rows = packed.compact(engine)
    finally:
        engine.dispose()
    print(f"packed {frames} raw frames and {rows} measurement and battery-state rows")
    return 0


def _safe_url(url: str) -> str:
    from sqlalchemy.engine import make_url

    return make_url(url).render_as_string(hide_password=True)


def _common(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--db", metavar="URL", help="database URL (default: settings, sqlite:///eqgw.db)"
    )
    p.add_argument("--config", metavar="TOML", help="fleet file (default: $EQGW_CONFIG)")


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """Add `replay` and `db` to the eqgw command line."""
    rp = subparsers.add_parser(
        "replay",
        help="load a CAN log into the history (idempotent)",
        description="Decode a python-can log (candump .log, .asc, .blf, .trc, .csv) and store "
        "it. Replaying the same file twice adds nothing.",
    )
    rp.add_argument("file", help="log file")
    rp.add_argument(
        "--vehicle",
        action="append",
        required=True,
        metavar="[CHANNEL=]ID",
        help="vehicle of the whole log, or of one log channel (repeat per channel)",
    )
    _common(rp)
    rp.add_argument(
        "--sa",
        type=parse_sas,
        default=None,
        metavar="30,31",
        help="equalizer source addresses (default: the vehicle's bus in --config, else 30)",
    )
    rp.add_argument("--no-raw", action="store_true", help="do not archive raw frames")
    rp.add_argument("--quiet", "-q", action="store_true", help="no progress bar")
    rp.add_argument("--json", action="store_true", help="print the summary as JSON")
    rp.set_defaults(func=_replay)

    ex = subparsers.add_parser(
        "export",
        help="write a vehicle's archived CAN frames to a log file",
        description="Write the raw archive of a vehicle (every equalizer frame kept) for a "
        "time range to a candump, ASC, BLF or MF4 file, with python-can's writers; "
        "`eqgw replay` and python-can read it back. The vehicle's buses are channels 0, 1, "
        "... in name order.",
    )
    ex.add_argument("vehicle", help="vehicle id")
    ex.add_argument(
        "--from", dest="from_", metavar="TIME", help="epoch s or ISO 8601 (default --to - 1 h)"
    )
    ex.add_argument("--to", metavar="TIME", help="epoch s or ISO 8601, not included (default now)")
    ex.add_argument(
        "--format",
        choices=["candump", "asc", "blf", "mf4"],
        help="default: from the --out file's suffix (.log, .asc, .blf, .mf4)",
    )
    ex.add_argument("--out", required=True, metavar="FILE", help="the log file to write")
    _common(ex)
    ex.set_defaults(func=_export)

    db = subparsers.add_parser("db", help="database maintenance")
    dbsub = db.add_subparsers(dest="db_command", metavar="ACTION")
    up = dbsub.add_parser("upgrade", help="apply the Alembic migrations")
    up.add_argument("revision", nargs="?", default="head")
    _common(up)
    up.set_defaults(func=_db_upgrade)
    pr = dbsub.add_parser("prune", help="delete history older than the retention settings")
    _common(pr)
    pr.set_defaults(func=_db_prune)
    co = dbsub.add_parser(
        "compact",
        help="pack the raw frames, measurements and battery states that are due now",
        description="Pack what the gateway packs in the background: the raw archive's "
        "minutes that ended a minute ago, and the measurements and battery states of the "
        "hours that ended an hour before the unit's newest data.",
    )
    _common(co)
    co.set_defaults(func=_db_compact)

    def _db_help(_args: argparse.Namespace) -> int:
        db.print_help()
        return 2

    db.set_defaults(func=_db_help)
