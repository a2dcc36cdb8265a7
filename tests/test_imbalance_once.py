"""Battery imbalance is computed once (`eqgw.fleet.diagnosis.Batteries`): the fleet view, the
diagnosis and the imbalance alert show the same B - A for the same readings, to the bit."""

from __future__ import annotations

from hypothesis import given, settings
from hypothesis import strategies as st

from eqgw.alerts.rules import CONDITIONS, Facts, builtin_rules
from eqgw.fleet.diagnosis import Batteries, diagnose

# The voltages record's raw counts times its scale, as the decoder makes them.
_RAW = st.integers(min_value=0, max_value=0xFFFA)


@settings(max_examples=400, deadline=None)
@given(_RAW, _RAW)
def test_diagnosis_and_alert_agree_with_the_one_computation(raw12: int, raw24: int) -> None:
    v12, v24 = raw12 * 0.001, raw24 * 0.001
    one = Batteries.of(v12, v24)
    diag = diagnose({"v12": v12, "v24": v24}, None)
    assert (diag["battery_a_v"], diag["battery_b_v"], diag["b_minus_a_v"]) == (
        one.a_v,
        one.b_v,
        one.imbalance_v,
    )
    rule = builtin_rules()["imbalance"]
    facts = Facts(
        latest={"voltages": (0.0, {"v12": v12, "v24": v24})}, flags=None, faults=frozenset()
    )
    seen = CONDITIONS["imbalance"].evaluate(rule.params, facts)
    assert seen.values["imbalance_v"] == one.imbalance_v
    assert (seen.values["battery_a_v"], seen.values["battery_b_v"]) == (one.a_v, one.b_v)


def test_one_rounding_not_two() -> None:
    """B - A rounded once from the readings: rounding B first and then B - A again gave a
    different last digit than the fleet view for readings like these."""
    v12, v24 = 12.0005, 24.0
    assert round(round(v24 - v12, 3) - v12, 3) == -0.002  # B rounded first, then B - A
    assert Batteries.of(v12, v24).imbalance_v == -0.001 == round((v24 - v12) - v12, 3)
