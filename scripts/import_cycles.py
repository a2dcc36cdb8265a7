"""Import cycles between eqgw's packages, from the module-level imports of app/ (ast).

Usage: python scripts/import_cycles.py [--modules] [--deferred]

An import counts when it runs as the module loads: at module level, or in a module-level
`if`/`try` (not under `if TYPE_CHECKING:`, not inside a function). Packages are the first
level under eqgw (`eqgw.config`, `eqgw.alerts`, ...); `--modules` looks at modules instead;
`--deferred` counts imports inside functions too (the cycles they hide).
Prints each strongly connected component of more than one node, and each edge inside it
with the importing module and line.
"""

from __future__ import annotations

import ast
import sys
from collections import defaultdict
from collections.abc import Iterator
from pathlib import Path

APP = Path(__file__).resolve().parents[1] / "app"
Edge = tuple[str, str, str, int]  # from node, to node, importing module, line


def module_name(path: Path) -> str:
    parts = ["eqgw", *path.relative_to(APP).with_suffix("").parts]
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _load_time(body: list[ast.stmt]) -> Iterator[ast.Import | ast.ImportFrom]:
    """Imports that run when the module is loaded."""
    for node in body:
        if isinstance(node, ast.Import | ast.ImportFrom):
            yield node
        elif isinstance(node, ast.If):
            test = ast.unparse(node.test)
            if "TYPE_CHECKING" not in test:
                yield from _load_time(node.body)
            yield from _load_time(node.orelse)
        elif isinstance(node, ast.Try):
            for block in (node.body, node.orelse, node.finalbody, *(h.body for h in node.handlers)):
                yield from _load_time(block)


def _anywhere(tree: ast.Module) -> Iterator[ast.Import | ast.ImportFrom]:
    """Every import, in functions too, but not under `if TYPE_CHECKING:`."""
    skip: set[int] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test):
            skip |= {id(n) for b in node.body for n in ast.walk(b)}
    for node in ast.walk(tree):
        if isinstance(node, ast.Import | ast.ImportFrom) and id(node) not in skip:
            yield node


def imports(path: Path, *, deferred: bool = False) -> Iterator[tuple[str, int]]:
    """Modules of eqgw that `path` imports at load time (`deferred`: in functions too), with
    the line."""
    me = module_name(path)
    package = me if path.name == "__init__.py" else me.rpartition(".")[0]
    tree = ast.parse(path.read_text(), str(path))
    for node in _anywhere(tree) if deferred else _load_time(tree.body):
        if isinstance(node, ast.Import):
            for alias in node.names:
                if alias.name.split(".")[0] == "eqgw":
                    yield alias.name, node.lineno
            continue
        base = node.module or ""
        if node.level:
            up = package.split(".")
            up = up[: len(up) - (node.level - 1)]
            base = ".".join([*up, base] if base else up)
        if base.split(".")[0] != "eqgw":
            continue
        for alias in node.names:
            # `from eqgw.x import y`: y may be a module of x; the edge goes to x either way.
            yield (f"{base}.{alias.name}" if base == "eqgw" else base), node.lineno


def node_of(module: str, *, modules: bool) -> str:
    if modules:
        return module
    parts = module.split(".")
    return ".".join(parts[:2])


def edges(*, modules: bool = False, deferred: bool = False) -> list[Edge]:
    out = []
    for path in sorted(APP.rglob("*.py")):
        me = module_name(path)
        for target, line in sorted(set(imports(path, deferred=deferred))):
            a, b = node_of(me, modules=modules), node_of(target, modules=modules)
            if a != b:
                out.append((a, b, me, line))
    return out


def cycles(*, modules: bool = False, deferred: bool = False) -> list[list[str]]:
    """Strongly connected components of more than one node (Tarjan), each sorted."""
    graph: dict[str, set[str]] = defaultdict(set)
    for a, b, _, _ in edges(modules=modules, deferred=deferred):
        graph[a].add(b)
        graph[b]
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    found: list[list[str]] = []
    sys.setrecursionlimit(10_000)

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in sorted(graph[v]):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                found.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return sorted(found)


def main() -> None:
    modules, deferred = "--modules" in sys.argv, "--deferred" in sys.argv
    all_edges = edges(modules=modules, deferred=deferred)
    found = cycles(modules=modules, deferred=deferred)
    for comp in found:
        print("cycle:", " <-> ".join(comp))
        members = set(comp)
        seen = set()
        for a, b, where, _line in all_edges:
            if a in members and b in members and (a, b, where) not in seen:
                seen.add((a, b, where))
                print(f"  {a} -> {b}  ({where})")
    print(f"{len(found)} cycles")


if __name__ == "__main__":
    main()
