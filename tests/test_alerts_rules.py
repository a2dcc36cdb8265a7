"""Alert rules without a database: conditions, hysteresis, the delay, validation, config, mutes."""

from __future__ import annotations

from typing import Any

import pytest

from eqgw.alerts.config import resolve_rules
from eqgw.alerts.repository import mute_covers
from eqgw.alerts.rules import (
    BUILTIN_RULES,
    Decision,
    Facts,
    RuleState,
    Verdict,
    builtin_rules,
    validate_rule,
)
from eqgw.config import ConfigError, load_settings

RULES = builtin_rules()


def facts(
    v12: float | None = None,
    v24: float | None = None,
    flags: dict[str, str] | None = None,
    faults: tuple[str, ...] = (),
    soc: tuple[float, float] | None = None,
    soh: tuple[float, float] | None = None,
) -> Facts:
    latest: dict[str, Any] = {}
    if v12 is not None and v24 is not None:
        latest["voltages"] = (0.0, {"v12": v12, "v24": v24, "i12": None, "i24": None})
    if soc is not None:
        latest["battery_states/2"] = (0.0, {"index": 2, "battery": "12v", "soc": soc[0]})
        latest["battery_states/4"] = (0.0, {"index": 4, "battery": "24v", "soc": soc[1]})
    if soh is not None:
        latest["battery_states/1"] = (0.0, {"index": 1, "battery": "12v", "soh": soh[0]})
        latest["battery_states/3"] = (0.0, {"index": 3, "battery": "24v", "soh": soh[1]})
    return Facts(latest=latest, flags=flags, faults=frozenset(faults))


@pytest.mark.parametrize(
    ("rule", "f", "verdict"),
    [
        # imbalance: B - A = V24 - 2 * V12
        ("imbalance", facts(12.6, 25.2), Verdict.CLEAR),
        ("imbalance", facts(12.5, 25.15), Verdict.FIRE),  # B - A = 0.15 V
        ("imbalance", facts(12.6, 25.28), Verdict.HOLD),  # 0.08 V: between 0.07 and 0.10
        ("imbalance", facts(12.8, 25.4), Verdict.FIRE),  # A above B by 0.2 V: abnormal
        ("imbalance", facts(12.6, 25.2, faults=("IMB",)), Verdict.FIRE),
        ("imbalance", facts(), Verdict.HOLD),
        ("undervoltage", facts(11.9, 23.9), Verdict.FIRE),
        ("undervoltage", facts(12.1, 24.2), Verdict.HOLD),
        ("undervoltage", facts(12.2, 24.4), Verdict.CLEAR),
        ("undervoltage", facts(12.2, 24.4, flags={"uvf": "active"}), Verdict.FIRE),
        ("overvoltage", facts(15.1, 30.2), Verdict.FIRE),
        ("overvoltage", facts(14.9, 29.8), Verdict.HOLD),
        ("overvoltage", facts(14.1, 28.2), Verdict.CLEAR),
        ("equalizer_fault", facts(faults=("EQFLT",)), Verdict.FIRE),
        ("equalizer_fault", facts(faults=("IMB",)), Verdict.CLEAR),
        ("offline", facts(faults=("OFFLINE",)), Verdict.FIRE),
        ("heartbeat_stuck", facts(faults=("HEARTBEAT_STUCK",)), Verdict.FIRE),
        ("jump_start_left_on", facts(flags={"state_can_jso": "active"}), Verdict.FIRE),
        ("jump_start_left_on", facts(flags={"state_can_jso": "inactive"}), Verdict.CLEAR),
        ("jump_start_left_on", facts(flags={"state_can_jso": "error"}), Verdict.HOLD),
        ("jump_start_left_on", facts(), Verdict.HOLD),
        ("soc_low", facts(soc=(39.0, 80.0)), Verdict.FIRE),
        ("soc_low", facts(soc=(42.0, 80.0)), Verdict.HOLD),
        ("soc_low", facts(soc=(45.0, 80.0)), Verdict.CLEAR),
        ("soc_low", facts(), Verdict.HOLD),  # a 70-series unit has no battery states
        ("soh_low", facts(soh=(90.0, 65.0)), Verdict.FIRE),
        ("shutdown_risk", facts(8.4, 16.9), Verdict.FIRE),  # battery A near 8 V
        ("shutdown_risk", facts(8.2, 16.4), Verdict.FIRE),  # and the system near 16 V
        ("shutdown_risk", facts(8.7, 17.5), Verdict.HOLD),
        ("shutdown_risk", facts(12.6, 25.2), Verdict.CLEAR),
    ],
)
def test_conditions(rule: str, f: Facts, verdict: Verdict) -> None:
    assert RULES[rule].observe(f).verdict is verdict


def test_values_carry_units_in_their_keys() -> None:
    obs = RULES["imbalance"].observe(facts(12.1, 24.43))
    assert obs.values == {
        "imbalance_v": 0.23, "battery_a_v": 12.1, "battery_b_v": 12.33, "v12": 12.1,
        "v24": 24.43,
    }  # fmt: skip
    assert "B - A = +0.23 V" in obs.message
    assert RULES["soc_low"].observe(facts(soc=(30.0, 50.0))).values == {
        "soc_12v_pct": 30.0,
        "soc_24v_pct": 50.0,
    }


def test_delay_fires_once_after_the_condition_held() -> None:
    st = RuleState()
    assert st.step(Verdict.FIRE, 0.0, 30.0, 0.0) is None
    assert st.step(Verdict.FIRE, 29.0, 30.0, 0.0) is None
    assert st.step(Verdict.FIRE, 30.0, 30.0, 0.0) is Decision.RAISE
    st.opened(1)
    for t in (31.0, 100.0, 1000.0):
        assert st.step(Verdict.FIRE, t, 30.0, 0.0) is None  # once, not per evaluation


def test_a_flickering_value_does_not_fire() -> None:
    st = RuleState()
    for t in range(0, 300, 2):
        verdict = Verdict.FIRE if t % 4 == 0 else Verdict.HOLD  # in and out of the band
        assert st.step(verdict, float(t), 30.0, 0.0) is None


def test_hysteresis_keeps_an_open_alert_open_between_the_levels() -> None:
    st = RuleState()
    assert st.step(Verdict.FIRE, 0.0, 0.0, 0.0) is Decision.RAISE
    st.opened(1)
    assert st.step(Verdict.HOLD, 1.0, 0.0, 10.0) is None
    assert st.step(Verdict.CLEAR, 2.0, 0.0, 10.0) is None
    assert st.step(Verdict.HOLD, 5.0, 0.0, 10.0) is None  # the clear delay starts again
    assert st.step(Verdict.CLEAR, 6.0, 0.0, 10.0) is None
    assert st.step(Verdict.CLEAR, 16.0, 0.0, 10.0) is Decision.CLEAR
    st.closed()
    assert not st.open and st.alert_id is None


def test_validation_reasons() -> None:
    assert validate_rule("imbalance", "warning", {"fire_v": 0.1, "clear_v": 0.07}) == []
    assert "kind 'x' is unknown" in validate_rule("x", "warning", {})[0]
    assert validate_rule("imbalance", "loud", {"fire_v": 0.1, "clear_v": 0.07})
    assert "params.clear_v is required" in validate_rule("imbalance", "info", {"fire_v": 1})[0]
    (reason,) = validate_rule("undervoltage", "info", {"fire_v24": 24.0, "clear_v24": 23.0})
    assert "clear_v24" in reason and "above" in reason
    assert validate_rule("fault", "info", {"fault": "X", "delay_s": -1})
    assert validate_rule("fault", "info", {"fault": "X", "delay_s": True})
    assert validate_rule("fault", "info", {"fault": ""})
    for rule in BUILTIN_RULES:
        assert validate_rule(rule.kind, rule.severity, rule.params) == [], rule.id


def test_config_overrides_and_new_rules() -> None:
    s = load_settings(
        alerts={
            "rules": {
                "imbalance": {"params": {"fire_v": 0.2, "clear_v": 0.1}, "targets": ["x"]},
                "soh_low": {"enabled": False},
                "ex24f": {"kind": "fault", "severity": "warning", "params": {"fault": "EX24F"}},
            }
        }
    )
    rules = resolve_rules(s.alerts)
    assert rules["imbalance"].params["fire_v"] == 0.2 and rules["imbalance"].delay_s == 30.0
    assert rules["imbalance"].targets == ("x",) and rules["imbalance"].source == "config"
    assert not rules["soh_low"].enabled
    assert rules["ex24f"].kind == "fault" and rules["undervoltage"].source == "builtin"
    for bad, word in [
        ({"new": {"kind": "fault"}}, "needs kind and severity"),
        ({"imbalance": {"kind": "fault"}}, "keeps its kind"),
        ({"imbalance": {"params": {"clear_v": 0.5}}}, "hysteresis"),
        ({"Bad Id": {"kind": "fault", "severity": "info", "params": {"fault": "X"}}}, "ids"),
        ({"imbalance": {"severity": "loud"}}, "severity"),
    ]:
        with pytest.raises(ConfigError, match=word):
            load_settings(alerts={"rules": bad})


def test_mute_windows() -> None:
    base = {"vehicle_id": "V", "rule": None, "starts_at": 100.0, "ends_at": 200.0}
    assert mute_covers(base, "V", "imbalance", 150.0)
    assert not mute_covers(base, "W", "imbalance", 150.0)
    assert not mute_covers(base, "V", "imbalance", 200.0)  # expired
    assert not mute_covers(base, "V", "imbalance", 50.0)
    assert not mute_covers({**base, "cancelled_at": 120.0}, "V", "x", 150.0)
    assert mute_covers({**base, "vehicle_id": None, "rule": "x"}, "W", "x", 150.0)
    assert not mute_covers({**base, "rule": "x"}, "V", "y", 150.0)
    # Quiet hours 22:00-06:00 UTC over a day: 1700000000 is 22:13 UTC.
    night = {**base, "starts_at": 0.0, "ends_at": 4e9, "daily_from_min": 22 * 60,
             "daily_to_min": 6 * 60}  # fmt: skip
    assert mute_covers(night, "V", "x", 1_700_000_000.0)
    assert mute_covers(night, "V", "x", 1_700_000_000.0 + 7 * 3600)  # 05:13
    assert not mute_covers(night, "V", "x", 1_700_000_000.0 + 12 * 3600)  # 10:13
    day = {**night, "daily_from_min": 8 * 60, "daily_to_min": 17 * 60}
    assert mute_covers(day, "V", "x", 1_700_000_000.0 + 12 * 3600)
