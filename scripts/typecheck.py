"""mypy on the package as it is imported: the folder `app/` checked as the package `eqgw`.

mypy names a module after its folder (`app/ingest/writer.py` would be `app.ingest.writer`),
and it cannot follow the editable install's import hook that maps `eqgw` to `app/`
(pyproject's `package-dir`); found through site-packages instead (a strict editable install's
link tree), the package would count as third-party and its errors be silenced. So this
script hands mypy every file of `app/` with its module name, as setuptools maps it, and
otherwise runs mypy as the command line does: the options of pyproject's `[tool.mypy]`, plus
any given here (`python scripts/typecheck.py --disallow-any-explicit`). Errors name the files
under `app/`. Exit status: 0 clean, 1 errors, 2 mypy could not run.

    python scripts/typecheck.py [mypy options]
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

from mypy import build
from mypy.errors import CompileError
from mypy.main import process_options
from mypy.modulefinder import BuildSource

ROOT = Path(__file__).resolve().parents[1]
PACKAGE, FOLDER = "eqgw", "app"


def sources(root: Path = ROOT) -> list[BuildSource]:
    """Every module of the package: `app/x/y.py` is `eqgw.x.y`, `app/x/__init__.py` is `eqgw.x`."""
    out = []
    for path in sorted((root / FOLDER).rglob("*.py")):
        parts = path.relative_to(root / FOLDER).with_suffix("").parts
        if parts[-1] == "__init__":
            parts = parts[:-1]
        out.append(BuildSource(str(path.relative_to(root)), ".".join((PACKAGE, *parts))))
    return out


def main(argv: list[str]) -> int:
    # The target given to the option parser only satisfies it; the sources are ours.
    _, options = process_options(["--config-file", str(ROOT / "pyproject.toml"), *argv, FOLDER])
    todo = sources()
    began = time.monotonic()
    try:
        result = build.build(todo, options)
    except CompileError as exc:  # a blocking error (a syntax error): mypy's own message
        print("\n".join(exc.messages), file=sys.stderr)
        return 2
    for line in result.errors:
        print(line)
    files = {line.split(":", 1)[0] for line in result.errors if ": error:" in line}
    errors = sum(": error:" in line for line in result.errors)
    took = time.monotonic() - began
    if errors:
        print(f"Found {errors} errors in {len(files)} files (checked {len(todo)} source files)")
        return 1
    print(f"Success: no issues found in {len(todo)} source files ({took:.0f} s)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
