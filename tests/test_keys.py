"""API keys: an optional expiry, the last-used time (recorded in batches, not per request) and
rotation (a new key, the old one revoked after an overlap), through the API and the CLI, on
both engines."""

from __future__ import annotations

import asyncio
import os
import re
import subprocess
import time
from pathlib import Path
from typing import Any

import pytest
from sqlalchemy import event

from eqgw.cli import main
from eqgw.security import repository as q
from eqgw.security.keys import KeyAuthenticator, Scope, create_key
from eqgw.store.engine import create_engine
from eqgw.store.migrate import upgrade_engine
from tests.api_helpers import served, wait_for
from tests.proc_helpers import eqgw, run

ROOT = Path(__file__).resolve().parent.parent


async def test_a_key_stops_at_its_expiry(db_url: str) -> None:
    """A key made to expire works until then and is a 401 after, though its lookup is
    cached (the cache holds the expiry, not only the answer)."""
    async with served(db_url, vehicles=1, key_cache_s=60) as s:
        # The API gives a key a minute at least; the store takes any expiry. A short life,
        # longer when a loaded machine answered the first use only after the expiry (then that
        # use proves nothing either way, and a new key is made).
        for life in (5.0, 15.0, 30.0):
            key_id, made_key = await asyncio.to_thread(
                create_key, s.rt.engine, f"short {life}", "viewer", expires_at=time.time() + life
            )
            listed = {
                k["id"]: k for k in (await s.client.get("/api/v1/keys", headers=s.auth())).json()
            }
            made = listed[key_id]
            assert made["expires_at"] is not None and made["active"]
            key = s.auth(made_key)
            asked = time.time()
            status = (await s.client.get("/api/v1/vehicles", headers=key)).status_code
            answered = time.time()
            if answered < made["expires_at"]:
                assert status == 200  # checked before the expiry: it works (and is cached)
                break
            # Answered after the expiry: 200 only if it was asked before it.
            assert status == 401 or (status == 200 and asked < made["expires_at"]), status
        else:
            raise AssertionError("no key's first use was answered within its life")

        async def refused() -> bool:
            return (await s.client.get("/api/v1/vehicles", headers=key)).status_code == 401

        await wait_for(refused, timeout=life + 10, what="the expired key refused")
        assert time.time() >= made["expires_at"]
        listed = {k["id"]: k for k in (await s.client.get("/api/v1/keys", headers=s.auth())).json()}
        assert listed[made["id"]]["active"] is False
        # An expiry in the past, or both forms at once, is refused.
        for body in ({"expires_at": time.time() - 10}, {"expires_at": 2e9, "expires_in_s": 5}):
            r = await s.client.post(
                "/api/v1/keys", json={"name": "x", "role": "viewer", **body}, headers=s.auth()
            )
            assert r.status_code == 422, (body, r.text)


async def test_last_used_is_recorded_in_batches(db_url: str) -> None:
    """50 requests with a key write nothing to api_keys; the next flush (every 10 s in a
    running gateway) writes its last use once, and the listing shows it."""
    async with served(db_url, vehicles=1) as s:
        key = await s.key("viewer", "reader")
        await asyncio.to_thread(s.rt.keys.flush_last_used)  # the admin key's use, made above
        updates: list[str] = []

        def count(_c: Any, _cur: Any, statement: str, *_a: Any) -> None:
            if statement.lstrip().upper().startswith("UPDATE API_KEYS"):
                updates.append(statement)

        event.listen(s.rt.engine, "before_cursor_execute", count)
        try:
            before = time.time()
            for _ in range(50):
                assert (await s.client.get("/api/v1/me", headers=s.auth(key))).status_code == 200
            assert updates == []
            await asyncio.to_thread(s.rt.keys.flush_last_used)
            assert len(updates) == 1, updates
        finally:
            event.remove(s.rt.engine, "before_cursor_execute", count)
        listed = (await s.client.get("/api/v1/keys", headers=s.auth())).json()
        used = next(k for k in listed if k["name"] == "reader")["last_used_at"]
        assert used is not None and used >= before


async def test_rotation_through_the_api(db_url: str) -> None:
    """Rotation makes a key like the old one (role, scope); the old one works through the
    overlap and is refused after it; an overlap of 0 revokes it at once."""
    async with served(db_url, vehicles=1, key_cache_s=60) as s:
        c = s.client
        r = await c.post(
            "/api/v1/keys",
            json={"name": "depot op", "role": "operator", "scope": {"vehicles": ["SIM-001"]}},
            headers=s.auth(),
        )
        old = r.json()
        r = await c.post(
            f"/api/v1/keys/{old['id']}/rotate", json={"overlap_s": 2}, headers=s.auth()
        )
        assert r.status_code == 201, r.text
        new = r.json()
        assert new["key"] != old["key"] and new["replaces"] == old["id"]
        assert (new["name"], new["role"], new["scope"]) == (old["name"], "operator", old["scope"])
        assert new["lineage"] == old["id"]
        assert new["old_key_ends_at"] <= time.time() + 2.5
        for k in (old["key"], new["key"]):
            me = await c.get("/api/v1/me", headers=s.auth(k))
            assert me.status_code == 200 and me.json()["scope"] == {
                "groups": [],
                "vehicles": ["SIM-001"],
            }

        async def old_refused() -> bool:
            return (await c.get("/api/v1/me", headers=s.auth(old["key"]))).status_code == 401

        await wait_for(old_refused, timeout=10, what="the old key refused after the overlap")
        assert (await c.get("/api/v1/me", headers=s.auth(new["key"]))).status_code == 200
        # The old key can no longer be rotated; the new one can, at once.
        r = await c.post(f"/api/v1/keys/{old['id']}/rotate", json={}, headers=s.auth())
        assert r.status_code == 404
        r = await c.post(
            f"/api/v1/keys/{new['id']}/rotate", json={"overlap_s": 0}, headers=s.auth()
        )
        assert r.status_code == 201
        assert (await c.get("/api/v1/me", headers=s.auth(new["key"]))).status_code == 401
        third = r.json()
        assert third["lineage"] == old["id"]
        assert (await c.get("/api/v1/me", headers=s.auth(third["key"]))).status_code == 200
        # Rotating needs an admin; the rotation is audited.
        op = s.auth(third["key"])
        assert (
            await c.post(f"/api/v1/keys/{third['id']}/rotate", json={}, headers=op)
        ).status_code == 403
        audit = (await c.get("/api/v1/audit", headers=s.auth())).json()["entries"]
        assert any(e["action"] == "key.rotate" and e["outcome"] == "accepted" for e in audit)


def _run(db_url: str, tmp_path: Path, *args: str) -> subprocess.CompletedProcess[str]:
    env = {k: v for k, v in os.environ.items() if not k.startswith("EQGW_")}
    env.update({"PYTHONPATH": str(ROOT), "EQGW_DATABASE_URL": db_url})
    return run(eqgw(*args), tmp_path, env, timeout=120)


KEY = re.compile(r"^(eqgw_\S+)$", re.M)


def test_keys_cli_scope_expiry_rotation(db_url: str, tmp_path: Path) -> None:
    """`eqgw keys create` with a scope and an expiry, `keys list` showing them, and `keys
    rotate` printing the new key while the old one ends after the overlap."""
    r = _run(db_url, tmp_path, "keys", "create", "--role", "ingest", "--name", "bus 7",
             "--vehicle", "SIM-007", "--group", "north", "--expires-in", "2h")  # fmt: skip
    assert r.returncode == 0, r.stderr
    key = KEY.search(r.stdout)
    assert key, r.stdout
    engine = create_engine(db_url)
    try:
        upgrade_engine(engine)
        auth = KeyAuthenticator(engine, cache_s=0)
        p = auth.lookup(key.group(1))
        assert p is not None and p.role == "ingest"
        assert p.scope == Scope.of(["north"], ["SIM-007"])
        assert p.ends_at is not None and 7100 < p.ends_at - time.time() <= 7200
        r = _run(db_url, tmp_path, "keys", "list")
        assert r.returncode == 0, r.stderr
        line = next(ln for ln in r.stdout.splitlines() if ln.endswith("bus 7"))
        assert "depot north, SIM-007" in line and "active" in line and "never" in line
        key_id = p.key_id
        r = _run(db_url, tmp_path, "keys", "rotate", str(key_id), "--overlap", "0")
        assert r.returncode == 0, r.stderr
        new = KEY.search(r.stdout)
        assert new and new.group(1) != key.group(1)
        assert auth.lookup(key.group(1)) is None
        p2 = auth.lookup(new.group(1))
        assert p2 is not None and p2.scope == p.scope and p2.lineage == key_id
        assert p2.ends_at is None  # no --expires-in: the new key does not expire
        r = _run(db_url, tmp_path, "keys", "rotate", str(key_id))
        assert r.returncode == 1 and "no active key" in r.stderr
        # Rotation may narrow the scope, never widen it.
        r = _run(db_url, tmp_path, "keys", "rotate", str(p2.key_id), "--vehicle", "SIM-008")
        assert r.returncode == 2 and "within the old key's" in r.stderr, r.stderr
        r = _run(db_url, tmp_path, "keys", "rotate", str(p2.key_id), "--vehicle", "SIM-007",
                 "--overlap", "0")  # fmt: skip
        assert r.returncode == 0, r.stderr
        narrowed = KEY.search(r.stdout)
        assert narrowed
        p3 = auth.lookup(narrowed.group(1))
        assert p3 is not None and p3.scope == Scope.of([], ["SIM-007"]) and p3.lineage == key_id
        r = _run(db_url, tmp_path, "keys", "create", "--role", "viewer", "--name", "x",
                 "--expires-in", "soon")  # fmt: skip
        assert r.returncode == 2 and "not a duration" in r.stderr
        # The overlap: rotated with the default day, the old key still works.
        kid, k = create_key(engine, "long", "viewer")
        r = _run(db_url, tmp_path, "keys", "rotate", str(kid))
        assert r.returncode == 0 and "keeps working until" in r.stdout
        assert auth.lookup(k) is not None
        with engine.connect() as conn:
            row = q.get_key(conn, kid)
        assert row is not None and 86000 < row["revoked_at"] - time.time() <= 86400
    finally:
        engine.dispose()


# Expiries that would lock a key's holder out at once (or never parse as a number), and
# overlaps that are not numbers: each a 422 naming the field, before anything is changed.
BAD_EXPIRES_IN: list[Any] = [5e-324, 0, 1, 59.9, -1, True, False, "3600", 1e308]
BAD_OVERLAPS: list[Any] = [False, True, "60", None, [], -1]


async def test_expiry_and_overlap_must_be_numbers_that_leave_time(db_url: str) -> None:
    """`{"expires_in_s": 5e-324, "overlap_s": false}` used to rotate a key into one already
    expired and revoke the old one at once. An expiry is a number at least a minute ahead, an
    overlap a number; anything else is a 422 with the reason, and the old key keeps working."""
    async with served(db_url, vehicles=1) as s:
        c, admin = s.client, s.auth()
        r = await c.post("/api/v1/keys", json={"name": "victim", "role": "viewer"}, headers=admin)
        old = r.json()
        rotate = f"/api/v1/keys/{old['id']}/rotate"
        r = await c.post(rotate, json={"expires_in_s": 5e-324, "overlap_s": False}, headers=admin)
        assert r.status_code == 422, r.text
        assert "expires_in_s" in r.json()["detail"] and "overlap_s" in r.json()["detail"]
        for bad in BAD_EXPIRES_IN:
            for path, body in ((rotate, {}), ("/api/v1/keys", {"name": "x", "role": "viewer"})):
                r = await c.post(path, json={**body, "expires_in_s": bad}, headers=admin)
                assert r.status_code == 422, (path, bad, r.text)
                assert "expires_in_s" in r.json()["detail"], r.text
        for bad in BAD_OVERLAPS:
            r = await c.post(rotate, json={"overlap_s": bad}, headers=admin)
            assert r.status_code == 422, (bad, r.text)
            assert "overlap_s" in r.json()["detail"], r.text
        for at in (time.time() + 30, time.time() - 10, True, "2000000000"):
            for path, body in ((rotate, {}), ("/api/v1/keys", {"name": "x", "role": "viewer"})):
                r = await c.post(path, json={**body, "expires_at": at}, headers=admin)
                assert r.status_code == 422, (path, at, r.text)
                assert "expires_at" in r.json()["detail"], r.text
        # Nothing was made or revoked: the old key works, no other key exists.
        assert (await c.get("/api/v1/me", headers=s.auth(old["key"]))).status_code == 200
        names = [k["name"] for k in (await c.get("/api/v1/keys", headers=admin)).json()]
        assert sorted(names) == ["first admin", "victim"], names
        # The limits themselves are accepted: a minute ahead, an overlap of 0 (whole numbers
        # or not).
        r = await c.post(
            "/api/v1/keys", json={"name": "m", "role": "viewer", "expires_in_s": 60}, headers=admin
        )
        assert r.status_code == 201, r.text
        r = await c.post(rotate, json={"expires_at": time.time() + 120, "overlap_s": 0.5},
                         headers=admin)  # fmt: skip
        assert r.status_code == 201, r.text
        assert (await c.get("/api/v1/me", headers=s.auth(r.json()["key"]))).status_code == 200


def _cli(capsys: pytest.CaptureFixture[str], *args: str) -> tuple[int, str, str]:
    """`eqgw ARGS` in this process: (exit code, stdout, stderr)."""
    try:
        code = main(list(args))
    except SystemExit as exc:  # argparse refusing an argument
        code = int(exc.code or 0)
    out = capsys.readouterr()
    return code, out.out, out.err


def test_keys_cli_refuses_expiries_that_lock_out(
    db_url: str, capsys: pytest.CaptureFixture[str]
) -> None:
    """The CLI's `--expires-in` is at least a minute (`--expires-in 5e-324` made a key that
    never worked), `--overlap` a number of seconds (or with a unit) from 0 to 30 days."""
    db = ("--db", db_url)
    for bad in ("5e-324", "0", "59", "1m-1", "nan", "inf", "-5"):
        code, _, err = _cli(capsys, "keys", "create", "--role", "viewer", "--name", "x", *db,
                            "--expires-in", bad)  # fmt: skip
        assert code == 2 and "--expires-in" in err, (bad, err)
    code, out, err = _cli(capsys, "keys", "create", "--role", "viewer", "--name", "v", *db)
    assert code == 0, err
    key = KEY.search(out)
    assert key
    engine = create_engine(db_url)
    try:
        auth = KeyAuthenticator(engine, cache_s=0)
        p = auth.lookup(key.group(1))
        assert p is not None
        assert [r["name"] for r in q.list_keys(engine.connect())] == ["v"]
        for args in (("--expires-in", "5e-324"), ("--overlap", "false"), ("--overlap", "nan"),
                     ("--overlap", "31d"), ("--overlap", "-1")):  # fmt: skip
            code, _, err = _cli(capsys, "keys", "rotate", str(p.key_id), *db, *args)
            assert code == 2 and args[0] in err, (args, err)
        assert auth.lookup(key.group(1)) is not None  # not rotated, not revoked
        code, _, err = _cli(capsys, "keys", "rotate", str(p.key_id), *db, "--expires-in", "1m",
                            "--overlap", "0")  # fmt: skip
        assert code == 0, err
        assert auth.lookup(key.group(1)) is None
    finally:
        engine.dispose()


def test_keys_cli_ingest_key_needs_a_scope(db_url: str, capsys: pytest.CaptureFixture[str]) -> None:
    """`eqgw keys create --role ingest` without `--vehicle` or `--group` made a fleet-wide
    forwarder key; now it needs them or `--all-vehicles`, and `keys list` marks fleet-wide
    ingest keys (those made before the rule too)."""
    db = ("--db", db_url)
    code, out, err = _cli(capsys, "keys", "create", "--role", "ingest", "--name", "fwd", *db)
    assert code == 2 and not KEY.search(out), out
    assert "--vehicle" in err and "--all-vehicles" in err, err
    code, _, err = _cli(capsys, "keys", "create", "--role", "ingest", "--name", "fwd", *db,
                        "--all-vehicles", "--vehicle", "SIM-001")  # fmt: skip
    assert code == 2 and "--all-vehicles" in err, err
    code, out, err = _cli(capsys, "keys", "create", "--role", "ingest", "--name", "relay", *db,
                          "--all-vehicles")  # fmt: skip
    assert code == 0 and KEY.search(out), err
    assert "ALL VEHICLES" in out, out
    code, _, err = _cli(capsys, "keys", "create", "--role", "viewer", "--name", "reader", *db)
    assert code == 0, err
    engine = create_engine(db_url)
    try:
        create_key(engine, "legacy", "ingest")  # as made before the rule: no scope
    finally:
        engine.dispose()
    code, out, err = _cli(capsys, "keys", "list", *db)
    assert code == 0, err
    lines = {ln.rsplit(None, 1)[-1]: ln for ln in out.splitlines()[1:]}
    assert "ALL VEHICLES" in lines["relay"] and "ALL VEHICLES" in lines["legacy"], out
    assert "all vehicles" in lines["reader"] and "ALL" not in lines["reader"], out
    assert "fwd" not in lines, out  # the refused ones made nothing
