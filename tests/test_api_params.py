"""Query parameters of the read endpoints: times checked alike everywhere, and a history that
holds more points than one answer carries is refused, never cut (SQLite and PostgreSQL)."""

from __future__ import annotations

import time
from typing import Any

import pytest

from eqgw.fleet import endpoints as fleet
from tests.api_helpers import served, wait_for
from tests.test_history_cache import _write

V = "/api/v1/vehicles"
TIMED = [
    f"{V}/SIM-001/history",
    f"{V}/SIM-001/status",
    f"{V}/SIM-001/faults",
    "/api/v1/faults",
    "/api/v1/audit",
]
# float() takes the first six (no time is NaN or infinite); the last two are no time at all.
BAD = ["nan", "NaN", "inf", "-inf", "infinity", "1e400", "bogus", "2024-02-31"]


async def test_every_endpoint_refuses_bad_times_naming_the_parameter(db_url: str) -> None:
    async with served(db_url, vehicles=1) as s:
        c = s.client

        async def stored() -> bool:
            r = await c.get(f"{V}/SIM-001/history?bucket=raw", headers=s.auth())
            return r.status_code == 200 and bool(r.json()["series"]["v12"])

        await wait_for(stored, what="stored measurements")  # so history answers past a 404
        wrong: list[tuple[str, dict[str, str], int, Any]] = []  # every case, not just the first
        for path in TIMED:
            for name in ("from", "to"):
                for bad in BAD:
                    r = await c.get(path, params={name: bad}, headers=s.auth())
                    body = r.json()
                    if not (
                        r.status_code == 422
                        and body["type"] == "invalid_time"
                        and f"`{name}`" in body["detail"]
                        and repr(bad) in body["detail"]
                    ):
                        wrong.append((path, {name: bad}, r.status_code, body))
            for order in (
                {"from": "200", "to": "100"},
                {"from": "100", "to": "100"},
                {"from": "2024-01-02T00:00:00Z", "to": "2024-01-01"},
            ):
                r = await c.get(path, params=order, headers=s.auth())
                body = r.json()
                if (r.status_code, body) != (
                    422,
                    {"type": "invalid_time", "detail": "`from` must be before `to`"},
                ):
                    wrong.append((path, order, r.status_code, body))
            # What was accepted before still is: epoch seconds, ISO 8601, one bound, no bound.
            now = time.time()
            for good in (
                {"from": str(now - 600), "to": str(now)},
                {"from": "2024-01-01T00:00:00Z", "to": "2024-01-02"},
                {"from": str(now - 60)},
                {"to": str(now)},
                {"from": "", "to": ""},
                {},
            ):
                r = await c.get(path, params=good, headers=s.auth())
                if r.status_code != 200:
                    wrong.append((path, good, r.status_code, r.text))
        assert not wrong, "\n".join(f"{w[0]} {w[1]}: {w[2]} {str(w[3])[:100]}" for w in wrong)


async def test_history_above_the_limit_is_refused_not_cut(
    db_url: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(fleet, "HISTORY_LIMIT", 5)
    async with served(db_url, vehicles=1) as s:
        c = s.client
        bus = next(iter(s.rt.ingest.live.of_vehicle("SIM-001"))).ref.bus
        now = time.time()
        day = now - now % 86400 - 3 * 86400  # a day of its own, long before the simulator's
        rows = [
            {"ts": day + 60 * i + 5, "v12": 12.0 + i / 10, "v24": 25.0, "i12": 0.0, "i24": 0.0}
            for i in range(12)
        ]
        _write(s.rt.engine, rows, key=(bus, 30), vehicle="SIM-001")
        hour = {"from": str(day), "to": str(day + 3600), "unit": "30"}

        async def get(**params: str) -> Any:
            return await c.get(f"{V}/SIM-001/history", params={**hour, **params}, headers=s.auth())

        async def written() -> bool:
            r = await get(bucket="1h", fields="v12")
            return r.status_code == 200 and [p["count"] for p in r.json()["series"]["v12"]] == [12]

        await wait_for(written, what="the written rows")
        # 12 raw points (and 12 one-minute buckets) of v12 in the hour: more than 5, refused.
        for params, what, wider in (
            ({"bucket": "raw"}, "raw points", "(1m, 15m, 1h, 1d)"),
            ({"bucket": "raw", "format": "csv"}, "raw points", "(1m, 15m, 1h, 1d)"),
            ({"bucket": "1m"}, "1m buckets", "(15m, 1h, 1d)"),
        ):
            for fields in ("v12", "v12,v24"):
                r = await get(fields=fields, **params)
                assert r.status_code == 422, (params, r.text)
                body = r.json()
                assert body["type"] == "too_many_points"
                assert body["limit"] == 5 and body["fields"] == fields.split(",")
                assert f"more than 5 {what} of {fields.replace(',', ', ')}" in body["detail"]
                assert f"shorter range or a wider bucket {wider}" in body["detail"]
        # Exactly the limit is answered whole: 5 raw points in the first 5 minutes.
        r = await get(bucket="raw", fields="v12,v24", to=str(day + 300))
        assert r.status_code == 200, r.text
        assert [p["value"] for p in r.json()["series"]["v12"]] == [12.0, 12.1, 12.2, 12.3, 12.4]
        assert len(r.json()["series"]["v24"]) == 5
        r = await get(bucket="15m", fields="v12")
        assert r.status_code == 200
        assert [p["count"] for p in r.json()["series"]["v12"]] == [12]


async def test_status_above_its_limit_is_refused_and_faults_say_when_cut(
    db_url: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    async with served(db_url, vehicles=1) as s:
        auth = s.auth()
        # The simulator's first status frame is a change: wait for one stored.
        url = f"{V}/SIM-001/status?from=0"

        async def stored() -> Any:
            r = await s.client.get(url, headers=auth)
            return r.status_code == 200 and r.json()["changes"]

        changes = await wait_for(stored, what="a stored status change")
        monkeypatch.setattr(fleet, "STATUS_LIMIT", len(changes) - 1)
        r = await s.client.get(url, headers=auth)
        assert r.status_code == 422 and r.json()["type"] == "too_many_points", r.text
        monkeypatch.setattr(fleet, "STATUS_LIMIT", 10_000)
        assert (await s.client.get(url, headers=auth)).status_code == 200
        # Faults: the list is capped, and says so; the counts cover every episode.
        s.sim.fail_equalizer("SIM-001")

        async def faults() -> Any:
            r = await s.client.get(f"{V}/SIM-001/faults", headers=auth)
            body = r.json()
            return body if body["total"] >= 1 else None

        body = await wait_for(faults, what="a fault episode")
        assert body["truncated"] is False and len(body["episodes"]) == body["total"]
        monkeypatch.setattr(fleet, "FAULTS_LIMIT", 0)
        body = (await s.client.get(f"{V}/SIM-001/faults", headers=auth)).json()
        assert body["truncated"] is True and body["episodes"] == [] and body["total"] >= 1
        assert sum(c["episodes"] for c in body["counts"].values()) == body["total"]
