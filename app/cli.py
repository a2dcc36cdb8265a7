"""The `eqgw` command line: each subsystem registers its own subcommands."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable, Sequence

# Each entry adds subcommands to the parser; modules are imported lazily so that
# `eqgw decode` does not pay for FastAPI or SQLAlchemy imports.
_REGISTRARS: list[str] = [
    "app.protocol.cli",
    "app.sim.cli",
    "app.ingest.cli",
    "app.api.cli",
    "app.forward.cli",
]


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="eqgw", description="Fleet gateway for Vanner VANN-Guard battery equalizers"
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    import importlib

    for modname in _REGISTRARS:
        try:
            mod = importlib.import_module(modname)
        except ModuleNotFoundError as exc:
            if exc.name == modname:
                continue  # subsystem not built yet
            raise
        register: Callable[[argparse._SubParsersAction[argparse.ArgumentParser]], None] = (
            mod.register
        )
        register(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    try:
        rc: int = args.func(args)
    except KeyboardInterrupt:
        return 130
    return rc


if __name__ == "__main__":
    sys.exit(main())
