"""`eqgw replay` and `eqgw db ...`: load logs into the history, migrate, prune."""

from __future__ import annotations

import argparse
import json
import sys
from typing import Any

from eqgw.protocol.cli import SALVAGED_EXIT, parse_sas


def _settings(args: argparse.Namespace) -> Any:
    from eqgw.config import ConfigError, load_settings

    overrides: dict[str, Any] = {}
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
    from eqgw.store.retention import prune

    settings = _settings(args)
    if settings is None:
        return 2
    r = settings.retention
    engine = create_engine(settings.database_url, deadlines=settings.db)
    try:
        result = prune(
            engine, raw_days=r.raw_days, rollup_days=r.rollup_days, batch_rows=r.batch_rows
        )
    finally:
        engine.dispose()
    print(f"deleted {result.total} rows in {result.batches} batches: {result.deleted}")
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

    db = subparsers.add_parser("db", help="database maintenance")
    dbsub = db.add_subparsers(dest="db_command", metavar="ACTION")
    up = dbsub.add_parser("upgrade", help="apply the Alembic migrations")
    up.add_argument("revision", nargs="?", default="head")
    _common(up)
    up.set_defaults(func=_db_upgrade)
    pr = dbsub.add_parser("prune", help="delete history older than the retention settings")
    _common(pr)
    pr.set_defaults(func=_db_prune)

    def _db_help(_args: argparse.Namespace) -> int:
        db.print_help()
        return 2

    db.set_defaults(func=_db_help)
