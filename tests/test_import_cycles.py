"""Import cycles between eqgw's packages (scripts/import_cycles.py reads app/ with ast).

The direction is one: `eqgw.config` (Settings) is the root every package may import; it
imports at load time only the layers its models are built from (`eqgw.bus`, `eqgw.protocol`)
and no domain. Two of its validators ask a domain's own check lazily (the alert rules, the
database URL); those packages import `eqgw.config` only for types, never as they load.
"""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path
from types import ModuleType

ROOT = Path(__file__).resolve().parents[1]


def _script() -> ModuleType:
    spec = importlib.util.spec_from_file_location(
        "import_cycles", ROOT / "scripts/import_cycles.py"
    )
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules.setdefault("import_cycles", module)
    spec.loader.exec_module(module)
    return module


ic = _script()

# Cycles that remain at load time, each with its reason. Nothing else may appear.
ALLOWED = {
    # The API layer and the domains: each domain's endpoints use eqgw.api's dependencies,
    # errors and schemas, and eqgw.api's Runtime (deps), websocket and exports use the
    # domains' services. Ending it means moving Runtime and the shared dependencies out of
    # eqgw.api into a package below the domains.
    ("eqgw.alerts", "eqgw.fleet", "eqgw.security", "eqgw.web"),
}
# What eqgw.config may import as it loads.
CONFIG_BUILT_FROM = {"eqgw.bus", "eqgw.protocol"}
# Domains whose own checks eqgw.config's validators call (inside the validator): the rules
# of [alerts.rules] (eqgw.alerts.config) and which database engines a URL may name
# (eqgw.store.engine.parse_url).
CONFIG_ASKS = {"eqgw.alerts", "eqgw.store"}


def test_no_new_cycle_at_load_time() -> None:
    assert {tuple(c) for c in ic.cycles()} == ALLOWED


def test_config_imports_no_domain_as_it_loads() -> None:
    loaded = {b for a, b, _, _ in ic.edges() if a == "eqgw.config"}
    assert loaded <= CONFIG_BUILT_FROM, loaded


def test_config_is_in_no_cycle_but_through_its_lazy_checks() -> None:
    """Counting imports inside functions too: eqgw.config reaches only the domains it asks
    for a check, and none of those imports eqgw.config as it loads; without those checks'
    edges, eqgw.config is in no cycle at all."""
    deferred = ic.edges(deferred=True)
    asked = {b for a, b, _, _ in deferred if a == "eqgw.config"} - CONFIG_BUILT_FROM
    assert asked == CONFIG_ASKS, asked
    back = {(a, where) for a, b, where, _ in ic.edges() if b == "eqgw.config" and a in asked}
    assert back == set(), back
    graph: dict[str, set[str]] = {}
    for a, b, _, _ in deferred:
        if not (a == "eqgw.config" and b in CONFIG_ASKS):
            graph.setdefault(a, set()).add(b)
    # Whatever eqgw.config reaches (load time or lazily, but for the asked checks) never
    # leads back to it.
    seen, todo = set(), list(graph.get("eqgw.config", ()))
    while todo:
        node = todo.pop()
        if node not in seen:
            seen.add(node)
            todo.extend(graph.get(node, ()))
    assert "eqgw.config" not in seen


def test_the_script_finds_a_cycle(tmp_path: Path) -> None:
    """The finder itself, on the graph it builds: a cycle of two modules is one component."""
    edges = [("a", "b", "a", 1), ("b", "a", "b", 1), ("b", "c", "b", 2)]
    original = ic.edges
    try:
        ic.edges = lambda **_kw: edges
        assert ic.cycles() == [["a", "b"]]
    finally:
        ic.edges = original
