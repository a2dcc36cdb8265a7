"""Write constraints.txt: the exact version of every package eqgw and its dev tools install,
read from the current environment (run it after installing or upgrading: pip install -e ".[dev]").

CI (.ci/run) and the Docker image install with `-c constraints.txt`, so a build installs what
was tested, not whatever is newest that day.
"""

from __future__ import annotations

import re
import sys
import tomllib
from importlib.metadata import PackageNotFoundError, distribution
from pathlib import Path

from packaging.requirements import Requirement

ROOT = Path(__file__).resolve().parents[1]
HEADER = """\
# Exact versions of everything eqgw and its dev tools install (runtime, extras, their
# dependencies), as tested. Made by `python scripts/constraints.py`; used as `pip install -c
# constraints.txt ...` by .ci/run and the Dockerfile. Not a requirements file: it only pins.
"""


def _canonical(name: str) -> str:
    return re.sub(r"[-_.]+", "-", name).lower()


def closure(roots: list[Requirement]) -> dict[str, str]:
    """name -> installed version of `roots` and everything they require, markers applied."""
    found: dict[str, str] = {}
    todo = [(r, frozenset(r.extras)) for r in roots]
    seen: set[tuple[str, frozenset[str]]] = set()
    while todo:
        req, extras = todo.pop()
        key = (_canonical(req.name), extras)
        if key in seen:
            continue
        seen.add(key)
        try:
            dist = distribution(req.name)
        except PackageNotFoundError:
            sys.exit(f"{req.name} is not installed: pip install -e '.[dev]' first")
        found[_canonical(dist.metadata["Name"])] = dist.version
        for text in dist.requires or []:
            sub = Requirement(text)
            if sub.marker is None or any(
                sub.marker.evaluate({"extra": e}) for e in (extras or {""})
            ):
                todo.append((sub, frozenset(sub.extras)))
    return found


def main() -> None:
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    roots = [Requirement(r) for r in project["dependencies"]]
    for extra in project.get("optional-dependencies", {}).values():
        roots += [Requirement(r) for r in extra]
    pins = closure(roots)
    pins.pop("eqgw", None)
    lines = [f"{name}=={version}" for name, version in sorted(pins.items())]
    (ROOT / "constraints.txt").write_text(HEADER + "\n".join(lines) + "\n")
    print(f"constraints.txt: {len(lines)} packages")


if __name__ == "__main__":
    main()
