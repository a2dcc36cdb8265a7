"""`eqgw vehicles import FILE.csv [--dry-run] [--replace]` and `eqgw vehicles export`: the
fleet in the database, from and to CSV (running gateways follow within a poll)."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

CLI_WHO = "eqgw vehicles import (command line)"


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """Add `eqgw vehicles` to the command line."""
    from eqgw.api.cli import _database_options

    v = subparsers.add_parser(
        "vehicles",
        help="manage the fleet's vehicles and buses in the database (CSV import and export)",
        description="The fleet lives in the database (the fleet file seeds an empty one): run "
        "these with the server's --config or --db. Running gateways apply a change within "
        "their poll (fleet.poll_s, 1 s).",
    )
    _database_options(v, top=True)
    sub = v.add_subparsers(dest="vehicles_command", metavar="ACTION")
    imp = sub.add_parser(
        "import",
        help="add and change vehicles from a CSV file (one transaction: a bad row changes nothing)",
        description="Read vehicles and their buses from CSV (one row per bus; docs/api.md "
        "names the columns). Every bad row is printed with its line number; when there is "
        "any, nothing is changed.",
    )
    imp.add_argument("file", metavar="FILE.csv", help="the CSV file ('-' for standard input)")
    imp.add_argument(
        "--dry-run", action="store_true", help="print what would change; change nothing"
    )
    imp.add_argument(
        "--replace",
        action="store_true",
        help="delete the vehicles the file leaves out (default: leave them untouched)",
    )
    imp.add_argument("--json", action="store_true", help="print the report as JSON")
    _database_options(imp, top=False)
    imp.set_defaults(func=vehicles_import)
    exp = sub.add_parser("export", help="print the fleet as CSV (what import reads)")
    exp.add_argument("file", nargs="?", metavar="FILE.csv", help="write here (default: stdout)")
    _database_options(exp, top=False)
    exp.set_defaults(func=vehicles_export)
    v.set_defaults(func=lambda _args: _help(v))


def _help(parser: argparse.ArgumentParser) -> int:
    parser.print_help()
    return 2


def vehicles_import(args: argparse.Namespace) -> int:
    """Entry point of `eqgw vehicles import`."""
    from sqlalchemy import Connection

    from eqgw.api.cli import _engine
    from eqgw.fleet import importer, registry
    from eqgw.security import repository as q
    from eqgw.security.audit import audit_entry

    try:
        raw = sys.stdin.read() if args.file == "-" else Path(args.file).read_text("utf-8-sig")
    except (OSError, UnicodeDecodeError) as exc:
        print(f"eqgw: cannot read {args.file}: {exc}", file=sys.stderr)
        return 2
    mode: registry.Mode = "replace" if args.replace else "merge"
    edit = importer.parse(raw)
    req = {"mode": mode, "file": str(args.file)[:200], "bytes": len(raw)}

    def audit(conn: Connection, outcome: registry.Outcome) -> None:
        for c in outcome.changes:
            if c.kind in ("added", "changed", "removed"):
                detail = c.kind + (f": {', '.join(c.fields)}" if c.fields else "")
                q.add_audit(
                    conn,
                    audit_entry(
                        None,
                        "vehicle.import",
                        outcome="accepted",
                        status=200,
                        detail=detail,
                        vehicle_id=c.vehicle_id,
                        target=f"vehicle {c.vehicle_id}",
                        request={"line": c.line, "mode": mode},
                        key_name=CLI_WHO,
                    ),
                )
        q.add_audit(
            conn,
            audit_entry(
                None,
                "vehicle.import",
                outcome="accepted",
                status=200,
                detail=outcome.summary(),
                target="fleet",
                request=req,
                key_name=CLI_WHO,
            ),
        )

    engine = _engine(args)
    try:
        outcome = registry.change(
            engine,
            edit,
            mode=mode,
            dry_run=args.dry_run,
            origin="eqgw vehicles import",
            audit=audit,
        )
    finally:
        engine.dispose()
    if args.json:
        print(json.dumps(outcome.report(), indent=2))
    else:
        _print(outcome)
    return 1 if outcome.problems else 0


def _print(outcome: Any) -> None:
    for p in outcome.problems:
        where = f"line {p.line}: " if p.line is not None else ""
        who = f"{p.vehicle_id}: " if p.vehicle_id else ""
        print(f"{where}{who}{p.reason}", file=sys.stderr)
    if outcome.problems:
        n = len(outcome.problems)
        print(f"eqgw: {n} bad row{'s' if n != 1 else ''}: nothing was changed", file=sys.stderr)
        return
    for c in outcome.of("added"):
        buses = f": buses {', '.join(c.buses_added)}" if c.buses_added else ""
        print(f"added     {c.vehicle_id} (line {c.line}){buses}")
    for c in outcome.of("changed"):
        parts = [f"+{n}" for n in c.buses_added] + [f"~{n}" for n in c.buses_changed]
        parts += [f"-{n}" for n in c.buses_removed]
        buses = f" ({' '.join(parts)})" if parts else ""
        print(f"changed   {c.vehicle_id} (line {c.line}): {', '.join(c.fields)}{buses}")
    for c in outcome.of("removed"):
        buses = f": buses {', '.join(c.buses_removed)}" if c.buses_removed else ""
        print(f"removed   {c.vehicle_id}{buses}")
    print(
        f"{len(outcome.of('unchanged'))} unchanged, {len(outcome.of('untouched'))} not in the "
        f"file and left as they are"
    )
    if outcome.dry_run:
        print("dry run: nothing was changed")
    elif outcome.applied:
        print(f"fleet version {outcome.version}: running gateways apply it within seconds")
    else:
        print("nothing to change")


def vehicles_export(args: argparse.Namespace) -> int:
    """Entry point of `eqgw vehicles export`."""
    from eqgw.api.cli import _engine
    from eqgw.fleet import importer, registry

    engine = _engine(args)
    try:
        fleet = registry.load_fleet(engine)
    finally:
        engine.dispose()
    text = importer.write(fleet)
    if args.file:
        Path(args.file).write_text(text, "utf-8")
    else:
        sys.stdout.write(text)
    return 0
