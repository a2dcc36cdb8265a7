"""CSV exports of fault episodes, alerts and the audit log, fleet-wide or of a depot, any
range, streamed in keyset pages, within the caller's scope, on SQLite and PostgreSQL.

The page size is made small here so that a few dozen rows cross many page boundaries: every
row comes exactly once, in id order, whatever the page size.
"""

from __future__ import annotations

import asyncio
import csv
import io
import time
from collections.abc import Callable
from typing import Any

import httpx
import pytest
from sqlalchemy import insert

from eqgw.alerts import repository as aq
from eqgw.alerts.endpoints import ALERT_COLUMNS
from eqgw.fleet.endpoints import FAULT_COLUMNS
from eqgw.security import repository as apiq
from eqgw.store import queries
from eqgw.store.models import FaultEpisode
from eqgw.web import csv_export
from tests.api_helpers import Served, uvicorn_serving, wait_for
from tests.support import web
from tests.test_scopes import DEPOTS, served_depots

V = "/api/v1"
PER_VEHICLE = 12  # rows of each kind per vehicle
T0 = 1_700_000_000.0  # the seeded rows' times: T0 + i * 100
# The seeded audit entries are years old: the gateway's audit retention (365 days), whose
# first prune runs moments after the start, would delete them under a running export.
KEEP_AUDIT = 0


def _rows(text: str) -> list[dict[str, str]]:
    return list(csv.DictReader(io.StringIO(text)))


def _seeded(text: str) -> list[dict[str, str]]:
    """The rows `_seed` wrote (the simulated fleet may add its own meanwhile)."""
    return [
        row
        for row in _rows(text)
        if row.get("action") == "seed"
        or row.get("message", "").startswith("test ")
        or float(row.get("started_at") or "inf") < T0 * 2
    ]


async def _seed(s: Served) -> None:
    """PER_VEHICLE fault episodes, alerts and audit entries per vehicle, interleaved, at
    T0 + i * 100 (an audit detail that a spreadsheet would run as a formula among them)."""

    async def stored() -> bool:
        units = await s.rt.db(queries.list_units)
        return {u["vehicle_id"] for u in units} >= set(DEPOTS)

    await wait_for(stored, what="every vehicle's units stored")
    units = {u["vehicle_id"]: u for u in await s.rt.db(queries.list_units)}

    def seed(conn: Any) -> None:
        for i in range(PER_VEHICLE):
            for vid in DEPOTS:
                u = units[vid]
                ts = T0 + i * 100
                conn.execute(
                    insert(FaultEpisode.__table__).values(
                        unit_id=u["id"], fault="OVF", spn=None, fmi=None, source="dm1",
                        state="closed", started_at=ts, last_seen_at=ts + 50, ended_at=ts + 50,
                        ended_by="cleared", occurrence_count=i + 1,
                    )
                )  # fmt: skip
                alert, _ = aq.raise_alert(
                    conn, vehicle_id=vid, bus=u["bus"], sa=100 + i, rule="imbalance",
                    severity="warning", message=f"test {i}", values={"v": i}, ts=ts, muted=False,
                )  # fmt: skip
                aq.clear_alert(conn, alert["id"], ts=ts + 50, by="test")
                apiq.add_audit(
                    conn,
                    {
                        "ts": ts, "key_id": None, "key_name": "seed", "role": "admin",
                        "action": "seed", "vehicle_id": vid, "target": None,
                        "request": {"i": i}, "outcome": "done", "status_code": 200,
                        "detail": "=HYPERLINK(\"http://x\")" if i == 0 else f"row {i}",
                        "command_id": None,
                    },
                )  # fmt: skip

    await s.rt.db(seed)


def _before_each_audit_page(
    monkeypatch: pytest.MonkeyPatch, before: Callable[[int], None]
) -> list[int]:
    """`list_audit` (the audit export's page read) runs `before(n)` before reading its n-th
    page (1, 2, ...); returns the list of the pages read so far."""
    real = apiq.list_audit
    pages: list[int] = []

    def wrapped(conn: Any, **kwargs: Any) -> list[dict[str, Any]]:
        pages.append(len(pages) + 1)
        before(pages[-1])
        return real(conn, **kwargs)

    monkeypatch.setattr(apiq, "list_audit", wrapped)
    return pages


@pytest.fixture(autouse=True)
def small_pages(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(csv_export, "PAGE", 5)


async def test_exports_are_whole_in_order_and_filtered(db_url: str) -> None:
    async with served_depots(db_url, audit_retention_days=KEEP_AUDIT) as s:
        await _seed(s)
        c, admin = s.client, s.auth()

        # Faults: every episode the JSON list holds, once each, in id order, with its
        # occurrence count; `?format=csv`, `Accept: text/csv` and /exports/faults agree.
        listed = (await c.get(f"{V}/faults", headers=admin)).json()
        r = await c.get(f"{V}/faults?format=csv", headers=admin)
        assert r.status_code == 200 and r.headers["content-type"].startswith("text/csv")
        assert r.headers["content-disposition"] == 'attachment; filename="faults.csv"'
        assert r.text.splitlines()[0] == ",".join(FAULT_COLUMNS)
        rows = _rows(r.text)
        ids = [int(row["id"]) for row in rows]
        assert ids == sorted(e["id"] for e in listed["episodes"]) and len(ids) == len(set(ids))
        assert len(ids) >= PER_VEHICLE * len(DEPOTS)
        seeded = _seeded(r.text)
        assert sorted(int(row["occurrence_count"]) for row in seeded if row["vehicle_id"] ==
                      "SIM-001") == list(range(1, PER_VEHICLE + 1))  # fmt: skip
        accept = await c.get(f"{V}/faults", headers={**admin, "Accept": "text/csv"})
        assert _seeded(accept.text) == seeded
        assert _seeded((await c.get(f"{V}/exports/faults", headers=admin)).text) == seeded
        one = _seeded((await c.get(f"{V}/vehicles/SIM-001/faults?format=csv", headers=admin)).text)
        assert one == [row for row in seeded if row["vehicle_id"] == "SIM-001"]
        # A depot, and a range: the episodes overlapping [T0 + 300, T0 + 500).
        north = _rows((await c.get(f"{V}/faults?format=csv&depot=north", headers=admin)).text)
        assert {row["vehicle_id"] for row in north} == {"SIM-001", "SIM-002"}
        assert len(north) == sum(row["vehicle_id"] != "SIM-003" for row in rows)
        window = f"from={T0 + 300}&to={T0 + 500}"
        ranged = _rows((await c.get(f"{V}/exports/faults?{window}", headers=admin)).text)
        assert [float(row["started_at"]) for row in ranged] == [T0 + 300] * 3 + [T0 + 400] * 3

        # Alerts: every alert, not a page of them, oldest first.
        r = await c.get(f"{V}/alerts?format=csv&limit=1", headers=admin)
        alerts = _rows(r.text)
        assert r.text.splitlines()[0] == ",".join(ALERT_COLUMNS)
        assert len(alerts) >= PER_VEHICLE * len(DEPOTS)
        assert [int(a["id"]) for a in alerts] == sorted({int(a["id"]) for a in alerts})
        assert {a["vehicle_name"] for a in alerts} == set(DEPOTS)
        first = next(a for a in alerts if a["message"] == "test 3")
        assert first["values"] == '{"v":3}' and first["muted"] == "false"
        south = _rows((await c.get(f"{V}/exports/alerts?depot=south", headers=admin)).text)
        assert {a["vehicle_id"] for a in south} == {"SIM-003"}
        assert len(south) == sum(a["vehicle_id"] == "SIM-003" for a in alerts)
        to = f"to={T0 + 250}"
        early = _rows((await c.get(f"{V}/alerts?format=csv&{to}", headers=admin)).text)
        assert sorted(a["message"] for a in early) == sorted(["test 0", "test 1", "test 2"] * 3)

        # The audit log: the range [T0 + 100, T0 + 300), a formula made harmless.
        operator = await s.key("operator")
        window = f"from={T0 + 100}&to={T0 + 300}"
        r = await c.get(f"{V}/audit?format=csv&{window}", headers=s.auth(operator))
        audit = _rows(r.text)
        assert [(e["vehicle_id"], e["request"]) for e in audit] == [
            (v, f'{{"i":{i}}}') for i in (1, 2) for v in DEPOTS
        ]
        everything = _rows((await c.get(f"{V}/exports/audit?depot=north", headers=admin)).text)
        harmful = [e for e in everything if e["action"] == "seed" and e["request"] == '{"i":0}']
        assert [e["detail"] for e in harmful] == ['\'=HYPERLINK("http://x")'] * 2
        viewer = await s.key("viewer")
        assert (await c.get(f"{V}/exports/audit", headers=s.auth(viewer))).status_code == 403
        assert (await c.get(f"{V}/audit?format=csv", headers=s.auth(viewer))).status_code == 403
        # Bad parameters are refused before anything is streamed.
        bad = await c.get(f"{V}/exports/faults?from=yesterday", headers=admin)
        assert bad.status_code == 422 and bad.json()["type"] == "invalid_time"


async def test_scoped_keys_export_their_depot_only(db_url: str) -> None:
    async with served_depots(db_url, audit_retention_days=KEEP_AUDIT) as s:
        await _seed(s)
        c, admin = s.client, s.auth()
        r = await c.post(
            f"{V}/keys",
            json={"name": "north ops", "role": "operator", "scope": {"groups": ["north"]}},
            headers=admin,
        )
        north = s.auth(r.json()["key"])
        for path in ("/faults?format=csv", "/alerts?format=csv", "/audit?format=csv",
                     "/exports/faults", "/exports/alerts", "/exports/audit"):  # fmt: skip
            mine = _seeded((await c.get(V + path, headers=north)).text)
            everything = _seeded((await c.get(V + path, headers=admin)).text)
            assert mine and {row["vehicle_id"] for row in mine} == {"SIM-001", "SIM-002"}, path
            assert mine == [row for row in everything if row["vehicle_id"] != "SIM-003"], path
            # Another depot's rows are not there to ask for: the answer is the header alone.
            sep = "&" if "?" in path else "?"
            other = await c.get(f"{V}{path}{sep}depot=south", headers=north)
            assert other.status_code == 200 and len(other.text.splitlines()) == 1, path
            assert "Southern" not in other.text and "SIM-003" not in other.text


def test_memory_is_one_page_not_the_range() -> None:
    """The stream reads a page at a time: a page function asked for more than PAGE rows, or
    for a page before the previous one was sent, fails this test."""
    sent: list[int] = []
    asked: list[tuple[int, int]] = []
    total = 23

    def page(conn: Any, after: int, limit: int) -> list[dict[str, Any]]:
        asked.append((after, limit))
        # Every earlier page was already handed on before this one is read.
        assert sent == list(range(1, after + 1)), (sent, after)
        return [{"id": i} for i in range(after + 1, min(after + limit, total) + 1)]

    class Db:
        async def db_page(self, fn: Any) -> Any:
            return fn(None)

    async def consume() -> None:
        async for chunk in csv_export.csv_pages(Db(), ["id"], page):  # type: ignore[arg-type]
            sent.extend(int(x) for x in chunk.decode().split() if x != "id")

    asyncio.run(consume())
    assert sent == list(range(1, total + 1))
    assert asked == [(0, 5), (5, 5), (10, 5), (15, 5), (20, 5)]


async def test_a_failure_midway_is_an_incomplete_answer_not_a_short_file(
    sqlite_url: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The database failing after the first pages were sent: the client gets an error while
    reading (the chunked body never ends), not a shorter file that looks whole."""
    async with served_depots(sqlite_url, audit_retention_days=KEEP_AUDIT) as s:
        await _seed(s)

        def fail_the_third(page: int) -> None:
            if page == 3:
                raise RuntimeError("database gone")

        _before_each_audit_page(monkeypatch, fail_the_third)
        async with (
            uvicorn_serving(s.app) as port,
            web.AsyncClient(base_url=f"http://127.0.0.1:{port}") as c,
        ):
            got = b""
            with pytest.raises(httpx.RemoteProtocolError):
                async with c.stream("GET", f"{V}/exports/audit", headers=s.auth()) as r:
                    assert r.status_code == 200
                    async for chunk in r.aiter_raw():
                        got += chunk
            # The header and two pages arrived before the failure.
            assert len(got.decode().splitlines()) == 1 + 2 * csv_export.PAGE


async def test_an_export_longer_than_the_request_deadline_is_whole(
    db_url: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Each page has the request's database deadline of its own: an export whose pages
    together take longer than one deadline (a large range, a slow client) is not cut."""
    # A page sleeps under a quarter of the deadline: the rest (2.3 s) is its margin on a loaded
    # machine (1.2 s was not enough for one page's read and commit beside two CPU hogs).
    deadline_s, nap_s = 3.0, 0.7
    async with served_depots(
        db_url, db_deadline_s=deadline_s, audit_retention_days=KEEP_AUDIT
    ) as s:
        await _seed(s)
        pages = _before_each_audit_page(monkeypatch, lambda _: time.sleep(nap_s))
        r = await s.client.get(f"{V}/exports/audit", headers=s.auth())
        assert r.status_code == 200, r.text
        assert len(pages) * nap_s > 2 * deadline_s  # the pages took two deadlines and more
        seeded = [row for row in _rows(r.text) if row["action"] == "seed"]
        assert len(seeded) == PER_VEHICLE * len(DEPOTS)
