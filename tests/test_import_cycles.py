"""Import cycles between eqgw's packages (scripts/import_cycles.py reads app/ with ast).

The direction is one: `eqgw.config` (Settings) is the root every package may import; it
imports at load time only the layers its models are built from (`eqgw.bus`, `eqgw.protocol`)
and no domain. Two of its validators ask a domain's own check lazily (the alert rules, the
database URL); those packages import `eqgw.config` only for types, never as they load.

The HTTP side is layered the same way: `eqgw.web` (what every route shares) below the domains
(security, commands, alerts, notify, fleet, forward), and `eqgw.api` (the composition) above
them. No cycle between packages remains at load time.
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
ALLOWED: set[tuple[str, ...]] = set()
# The domains: each sits on eqgw.web and below eqgw.api, which composes them.
DOMAINS = {
    "eqgw.alerts", "eqgw.commands", "eqgw.fleet", "eqgw.forward", "eqgw.notify", "eqgw.security",
}  # fmt: skip
# The composition: the app, its lifespan, the websocket, exports, health, metrics, the CLI.
COMPOSITION = {"eqgw.api", "eqgw.main", "eqgw.cli"}
# What eqgw.config may import as it loads.
CONFIG_BUILT_FROM = {"eqgw.bus", "eqgw.protocol"}
# Domains whose own checks eqgw.config's validators call (inside the validator): the rules
# of [alerts.rules] (eqgw.alerts.config) and which database engines a URL may name
# (eqgw.store.engine.parse_url).
CONFIG_ASKS = {"eqgw.alerts", "eqgw.store"}


def test_no_new_cycle_at_load_time() -> None:
    assert {tuple(c) for c in ic.cycles()} == ALLOWED


def test_web_sits_below_the_domains_and_the_composition() -> None:
    """eqgw.web (errors, responses, shared schemas, `Runtime`, CSV streaming) imports no
    domain and nothing of the composition as it loads (the domains' types it names are
    imported under TYPE_CHECKING)."""
    above = {(b, where) for a, b, where, _ in ic.edges() if a == "eqgw.web"}
    assert {(b, where) for b, where in above if b in DOMAINS | COMPOSITION} == set(), above


def test_domains_import_no_part_of_the_composition_as_they_load() -> None:
    up = {(a, b, where) for a, b, where, _ in ic.edges() if a in DOMAINS and b in COMPOSITION}
    assert up == set(), up


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
