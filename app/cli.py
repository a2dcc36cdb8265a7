"""The `eqgw` command line: each subsystem registers its own subcommands."""

from __future__ import annotations

import argparse
import os
import sys
from collections.abc import Callable, Sequence

# Each entry adds subcommands to the parser; modules are imported lazily so that
# `eqgw decode` does not pay for FastAPI or SQLAlchemy imports.
_REGISTRARS: list[str] = [
    "eqgw.protocol.cli",
    "eqgw.sim.cli",
    "eqgw.ingest.cli",
    "eqgw.api.cli",
    "eqgw.forward.cli",
    "eqgw.fleet.cli",
]


def _add_logging_options(parser: argparse.ArgumentParser, top: bool) -> None:
    # On the top parser they carry the defaults; on each command they default to nothing, so
    # `eqgw --log-level info serve` and `eqgw serve --log-level info` mean the same.
    from eqgw.logs import FORMATS, LEVELS

    parser.add_argument(
        "--log-level",
        choices=LEVELS,
        default=os.environ.get("EQGW_LOG_LEVEL", "warning") if top else argparse.SUPPRESS,
        help="least severe log records shown (default warning, or EQGW_LOG_LEVEL)",
    )
    parser.add_argument(
        "--log-format",
        choices=FORMATS,
        default=os.environ.get("EQGW_LOG_FORMAT", "text") if top else argparse.SUPPRESS,
        help="text lines or one JSON object per line (default text, or EQGW_LOG_FORMAT)",
    )


def _commands(parser: argparse.ArgumentParser) -> list[argparse.ArgumentParser]:
    """Every parser below `parser` (commands and their actions)."""
    found: list[argparse.ArgumentParser] = []
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for child in action.choices.values():
                found.append(child)
                found.extend(_commands(child))
    return found


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="eqgw", description="Fleet gateway for Vanner VANN-Guard battery equalizers"
    )
    from eqgw import version

    parser.add_argument("--version", action="version", version=f"eqgw {version()}")
    _add_logging_options(parser, top=True)
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
    for command in _commands(parser):
        _add_logging_options(command, top=False)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    from eqgw.logs import FORMATS, LEVELS, configure_logging

    # The environment's defaults are not checked by argparse's choices.
    level, fmt = str(args.log_level).lower(), str(args.log_format).lower()
    if level not in LEVELS or fmt not in FORMATS:
        parser.error(f"log level {level!r} or format {fmt!r} is not one of {LEVELS} / {FORMATS}")
    configure_logging(level, fmt)
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
