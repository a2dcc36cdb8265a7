"""The alert engine and delivery in /metrics and /readyz; alert writes rate limited per key."""

from __future__ import annotations

import socket
from typing import Any

from prometheus_client.parser import text_string_to_metric_families
from sqlalchemy import Engine

from eqgw.api.metrics import Metrics
from tests.alerts_helpers import Rig
from tests.api_helpers import Served, served, wait_for

A = "/api/v1/alerts"
EQ = ("equalizer_fault", "critical")


def samples(text: str) -> dict[tuple[str, tuple[tuple[str, str], ...]], float]:
    """Every sample of an exposition by (name, sorted labels)."""
    return {
        (s.name, tuple(sorted(s.labels.items()))): s.value
        for family in text_string_to_metric_families(text)
        for s in family.samples
    }


def value(got: dict[Any, float], name: str, **labels: str) -> float | None:
    return got.get((name, tuple(sorted(labels.items()))))


def _labels(rule: str, severity: str) -> dict[str, str]:
    return {"rule": rule, "severity": severity}


async def test_engine_figures_in_the_exposition(engine: Engine) -> None:
    """The equalizer-fault scenario driven step by step: two units fail at 60 s and are
    repaired 15 min later; the exposition counts both raises, both clears and the open ones."""
    rig = Rig(engine, scenario="equalizer-fault")
    metrics = Metrics()
    off = samples(metrics.exposition(None).decode())
    assert value(off, "eqgw_alert_engine_running") == 0.0
    assert value(off, "eqgw_alerts_open", severity="critical") is None
    await rig.start()
    try:
        await rig.run(120, step=1.0)
        got = samples(metrics.exposition(rig.engine).decode())
        assert value(got, "eqgw_alerts_raised_total", **_labels(*EQ)) == 2
        assert value(got, "eqgw_alerts_cleared_total", **_labels(*EQ)) is None
        assert value(got, "eqgw_alerts_open", severity="critical") == 2
        assert value(got, "eqgw_alerts_open", severity="info") == 0
        assert value(got, "eqgw_alert_rules") == len(rig.engine.rules)
        assert (value(got, "eqgw_alert_evaluations_total") or 0) > 0
        assert value(got, "eqgw_alert_engine_resyncs_total") == 0
        assert value(got, "eqgw_alert_engine_db_failures_total") == 0
        assert value(got, "eqgw_alert_engine_backlog_events") == 0
        # Driven by hand (start(run=False)): the engine's loops are not running.
        assert value(got, "eqgw_alert_engine_running") == 0.0
        await rig.run(16 * 60, step=1.0)
        got = samples(metrics.exposition(rig.engine).decode())
    finally:
        await rig.stop()
    assert value(got, "eqgw_alerts_raised_total", **_labels(*EQ)) == 2
    assert value(got, "eqgw_alerts_cleared_total", **_labels(*EQ)) == 2
    assert value(got, "eqgw_alerts_open", severity="critical") == 0
    # The counters agree with the database.
    rows = rig.alerts()
    raised = sum(v for (n, _), v in got.items() if n == "eqgw_alerts_raised_total")
    cleared = sum(v for (n, _), v in got.items() if n == "eqgw_alerts_cleared_total")
    assert raised == len(rows)
    assert cleared == sum(1 for a in rows if a["cleared_at"] is not None)


async def test_a_resync_is_counted(engine: Engine) -> None:
    rig = Rig(engine, 1, hub_queue=3)
    await rig.start()
    try:
        await rig.run(5, step=1.0)
        got = samples(Metrics().exposition(rig.engine).decode())
    finally:
        await rig.stop()
    assert (value(got, "eqgw_alert_engine_resyncs_total") or 0) >= 1


def _closed_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port: int = s.getsockname()[1]
    return port


async def _metrics(s: Served) -> dict[Any, float]:
    r = await s.client.get("/metrics", headers=s.auth())
    assert r.status_code == 200
    return samples(r.text)


async def test_metrics_and_readyz_of_a_running_gateway(db_url: str) -> None:
    """A simulated equalizer fails and is repaired while the only webhook's receiver is down:
    /metrics counts the alert raised and cleared, /readyz shows the engine running and the
    delivery failing, and stays ready (the receiver's problem is reported, not ours)."""
    config = {"webhook_allow_networks": "127.0.0.0/8"}
    async with served(db_url, vehicles=1, config=config) as s:
        r = await s.client.get("/readyz", headers=s.auth())
        assert r.status_code == 200, r.text
        body = r.json()
        assert body["ready"] is True
        assert body["alerts"]["enabled"] is True and body["alerts"]["running"] is True, body
        assert body["alerts"]["rules"] == 11 and "last_error" in body["alerts"]
        hooks = body["delivery"]["webhooks"]
        assert hooks["running"] is True and hooks["last_attempt_error"] is None, body
        assert value(await _metrics(s), "eqgw_alert_engine_running") == 1.0

        url = f"http://127.0.0.1:{_closed_port()}/hook"
        r = await s.client.post(
            "/api/v1/webhooks",
            json={"name": "down", "url": url, "rules": ["equalizer_fault"]},
            headers=s.auth(),
        )
        assert r.status_code == 201, r.text
        s.sim.fail_equalizer("SIM-001")

        async def raised() -> dict[Any, float] | None:
            got = await _metrics(s)
            n = value(got, "eqgw_alerts_raised_total", **_labels(*EQ))
            return got if n == 1 else None

        got = await wait_for(raised, timeout=90, what="the raise in /metrics")
        assert (value(got, "eqgw_alerts_open", severity="critical") or 0) >= 1

        async def failing() -> dict[str, Any] | None:
            r = await s.client.get("/readyz", headers=s.auth())
            assert r.status_code == 200, r.text
            b: dict[str, Any] = r.json()
            hooks = b["delivery"]["webhooks"]
            # `pending` is recounted at the end of the round that made the attempt.
            return b if hooks["last_attempt_error"] and hooks["pending"] >= 1 else None

        body = await wait_for(failing, timeout=60, what="a failed webhook attempt in /readyz")
        assert body["ready"] is True, body
        hooks = body["delivery"]["webhooks"]
        assert hooks["running"] is True, body
        failed = hooks["last_attempt_error"]
        assert failed["webhook"] == "down" and failed["error"], body
        # The receiver's failure is its own; the dispatcher's `last_error` is for ours (the
        # database), so it is not the refused connection.
        assert hooks["last_error"] != failed["error"], body
        got = await _metrics(s)
        assert (value(got, "eqgw_webhook_attempts_total", outcome="retried") or 0) >= 1
        assert value(got, "eqgw_webhook_round_failures_total") is not None

        s.sim.restore_equalizer("SIM-001")

        async def cleared() -> dict[Any, float] | None:
            got = await _metrics(s)
            n = value(got, "eqgw_alerts_cleared_total", **_labels(*EQ))
            return got if n == 1 else None

        got = await wait_for(cleared, timeout=90, what="the clear in /metrics")
        assert value(got, "eqgw_alerts_raised_total", **_labels(*EQ)) == 1
        (alert,) = (
            await s.client.get(A, params={"rule": "equalizer_fault"}, headers=s.auth())
        ).json()["alerts"]
        assert alert["state"] == "cleared", alert
        body = (await s.client.get("/readyz", headers=s.auth())).json()
        assert body["ready"] is True and body["alerts"]["running"] is True, body


async def test_alert_writes_are_rate_limited_per_key_and_audited(db_url: str) -> None:
    async with served(db_url, vehicles=1, write_rate=3, write_window_s=600) as s:
        # The admin key's first two writes.
        ann, bob = await s.key("operator", "Ann"), await s.key("operator", "Bob")
        s.sim.fail_equalizer("SIM-001")

        async def raised() -> list[dict[str, Any]]:
            r = await s.client.get(
                A, params={"rule": "equalizer_fault", "state": "open"}, headers=s.auth()
            )
            alerts: list[dict[str, Any]] = r.json()["alerts"]
            return alerts

        (alert,) = await wait_for(raised, timeout=90, what="equalizer_fault alert")
        ack = f"{A}/{alert['id']}/acknowledge"
        # Refused writes count too, as for commands: two unknown alerts, then the real one.
        for _ in range(2):
            r = await s.client.post(f"{A}/999999/acknowledge", json={}, headers=s.auth(ann))
            assert r.status_code == 404
        r = await s.client.post(ack, json={"comment": "on it"}, headers=s.auth(ann))
        assert r.status_code == 200, r.text
        r = await s.client.post(ack, json={"comment": "again"}, headers=s.auth(ann))
        assert r.status_code == 429, r.text
        assert r.json()["type"] == "rate_limited" and "retry in" in r.json()["detail"]
        assert 1 <= int(r.headers["Retry-After"]) <= 600
        # Per key: Bob is not limited (and is told it is already acknowledged).
        r = await s.client.post(ack, json={}, headers=s.auth(bob))
        assert r.status_code == 409, r.text

        # The admin's third write goes through; the rule and mute writes after it do not.
        r = await s.client.post(
            f"{A}/mutes", json={"vehicle_id": "SIM-001", "duration_s": 600}, headers=s.auth()
        )
        assert r.status_code == 201, r.text
        mute_id = r.json()["id"]
        rule = {"id": "ex24f", "kind": "fault", "severity": "warning", "params": {"fault": "EX24F"}}
        limited = [
            ("POST", f"{A}/rules", rule),
            ("PATCH", f"{A}/rules/imbalance", {"severity": "critical"}),
            ("DELETE", f"{A}/rules/ex24f", None),
            ("POST", f"{A}/mutes", {"duration_s": 60}),
            ("DELETE", f"{A}/mutes/{mute_id}", None),
        ]
        for method, url, body in limited:
            r = await s.client.request(method, url, json=body, headers=s.auth())
            assert r.status_code == 429, (method, url, r.text)
            assert int(r.headers["Retry-After"]) >= 1
        rules = (await s.client.get(f"{A}/rules", headers=s.auth())).json()["rules"]
        assert "ex24f" not in {x["id"] for x in rules}
        assert next(x for x in rules if x["id"] == "imbalance")["severity"] == "warning"

        r = await s.client.get("/api/v1/audit", headers=s.auth())
        entries = r.json()["entries"]
        refused = {(e["key_name"], e["action"]) for e in entries if e["status_code"] == 429}
        assert refused == {
            ("Ann", "alert.acknowledge"), ("first admin", "alert_rule.create"),
            ("first admin", "alert_rule.update"), ("first admin", "alert_rule.delete"),
            ("first admin", "alert_mute.create"), ("first admin", "alert_mute.cancel"),
        }  # fmt: skip
        (ann_429,) = [e for e in entries if e["key_name"] == "Ann" and e["status_code"] == 429]
        assert ann_429["outcome"] == "refused" and ann_429["target"] == f"alert {alert['id']}"
        assert ann_429["request"] == {"comment": "again"}
