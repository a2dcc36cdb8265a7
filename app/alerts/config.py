"""The rules a gateway starts with: the built-in ones with the config file's changes, plus its
own rules."""

from __future__ import annotations

import re
from dataclasses import replace
from typing import TYPE_CHECKING

from eqgw.alerts.rules import Rule, builtin_rules, validate_rule

if TYPE_CHECKING:
    from eqgw.config import AlertSettings

RULE_ID = re.compile(r"^[a-z0-9][a-z0-9_.-]{0,63}$")


def resolve_rules(settings: AlertSettings) -> dict[str, Rule]:
    """Built-in rules updated by `[alerts.rules.<id>]`, and the file's new rules; ValueError
    naming the rule when one is invalid."""
    rules = builtin_rules()
    for rule_id, cfg in settings.rules.items():
        if not RULE_ID.match(rule_id):
            raise ValueError(f"alerts.rules.{rule_id}: ids are 1-64 of a-z 0-9 _ . -")
        base = rules.get(rule_id)
        if base is None:
            if cfg.kind is None or cfg.severity is None:
                raise ValueError(f"alerts.rules.{rule_id}: a new rule needs kind and severity")
            base = Rule(rule_id, cfg.kind, cfg.severity, source="config")
        elif cfg.kind is not None and cfg.kind != base.kind:
            raise ValueError(
                f"alerts.rules.{rule_id}: a built-in rule keeps its kind ({base.kind})"
            )
        rule = replace(
            base,
            severity=cfg.severity or base.severity,
            enabled=base.enabled if cfg.enabled is None else cfg.enabled,
            params={**base.params, **cfg.params},
            targets=tuple(cfg.targets) if cfg.targets is not None else base.targets,
            description=cfg.description or base.description,
            source="config",
        )
        problems = validate_rule(rule.kind, rule.severity, rule.params)
        if problems:
            raise ValueError(f"alerts.rules.{rule_id}: " + "; ".join(problems))
        rules[rule_id] = rule
    return rules
