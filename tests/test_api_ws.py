"""The websocket: snapshot on subscribe, live updates, command states, slow clients dropped,
subscribe/unsubscribe, revoked keys, binary frames."""

from __future__ import annotations

import json
import time
import warnings
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any

import anyio
import pytest
from starlette.websockets import WebSocketDisconnect

with warnings.catch_warnings():
    # Starlette wants httpx2 for its test client; httpx works and is what is installed.
    warnings.simplefilter("ignore")
    from starlette.testclient import TestClient

from eqgw.config import Settings
from eqgw.ingest.events import LIVE, STATUS_CHANGE, Event, UnitRef
from eqgw.main import create_app
from eqgw.security import repository as q
from eqgw.sim.clock import RealtimeClock
from eqgw.sim.fleet import SimulatedFleet
from eqgw.web.settings import ApiSettings
from tests.api_helpers import heap_frozen


def _app(url: str, **api: object) -> tuple[TestClient, list[str]]:
    keys: list[str] = []
    sim = SimulatedFleet(2, seed=1, clock=RealtimeClock(4.0))
    app = create_app(
        Settings(database_url=url), api=ApiSettings(**api), sim=sim, on_first_key=keys.append
    )
    return TestClient(app), keys


def test_snapshot_then_updates_then_command_states(sqlite_url: str) -> None:
    client, keys = _app(sqlite_url)
    with heap_frozen(), client:
        deadline = time.monotonic() + 30
        while len(client.app.state.rt.ingest.live.units) < 2:  # type: ignore[attr-defined]
            assert time.monotonic() < deadline
            time.sleep(0.05)
        with client.websocket_connect(f"/api/v1/ws?key={keys[0]}&vehicles=SIM-001") as ws:
            snap = _recv(ws)
            assert snap["type"] == "snapshot" and snap["vehicle_id"] == "SIM-001"
            assert snap["units"][0]["latest"]
            msgs = _until(ws, lambda m: m["type"] == "live")
            assert {m["vehicle_id"] for m in msgs} == {"SIM-001"}
            r = client.post(
                "/api/v1/vehicles/SIM-001/commands",
                json={"jump_start_override": True},
                headers={"Authorization": f"Bearer {keys[0]}"},
            )
            assert r.status_code == 202
            # Only this command's: the gateway's own identification requests of the unit come
            # and go on the same socket.
            ours = [
                m["data"]["state"]
                for m in _until(
                    ws,
                    lambda m: (
                        m["type"] == "command"
                        and m["data"]["id"] == r.json()["id"]
                        and m["data"]["state"] == "confirmed"
                    ),
                    timeout=30,
                )
                if m["type"] == "command" and m["data"]["id"] == r.json()["id"]
            ]
            states = ours
            assert states[0] == "queued" and "sending" in states


def test_no_key_is_refused(sqlite_url: str) -> None:
    client, _ = _app(sqlite_url)
    with heap_frozen(), client, client.websocket_connect("/api/v1/ws") as ws:
        assert _recv(ws)["type"] == "error"
        with pytest.raises(WebSocketDisconnect) as exc:
            _recv(ws)
        assert exc.value.code == 4401


def test_slow_client_is_dropped_with_a_reason(sqlite_url: str) -> None:
    client, keys = _app(sqlite_url, ws_queue=20)
    with heap_frozen(), client:
        rt = client.app.state.rt  # type: ignore[attr-defined]
        with client.websocket_connect(f"/api/v1/ws?key={keys[0]}&vehicles=SIM-002") as ws:
            assert _recv(ws)["type"] == "snapshot"
            ref = UnitRef("SIM-002", "SIM-002/sim", 30)

            def burst() -> None:
                # Faster than any client reads: published in one go on the event loop.
                for i in range(500):
                    rt.ingest.hub.publish(Event(LIVE, ref, float(i), {"slot": "x", "fields": {}}))

            client.portal.call(burst)  # type: ignore[union-attr]
            with pytest.raises(WebSocketDisconnect) as exc:
                # Each read bounded; the close must come before 10 s without one.
                _until(ws, lambda m: m["type"] == "error" and m["reason"].startswith("slow"))
                _until(ws, lambda m: False)
            assert exc.value.code == 1008


# -- subscribe / unsubscribe, revocation, binary frames -------------------------------------


@contextmanager
def _running(url: str, **api: object) -> Iterator[tuple[TestClient, str]]:
    """The app running with both simulated vehicles online; yields (client, admin key)."""
    client, keys = _app(url, **api)
    with heap_frozen(), client:
        deadline = time.monotonic() + 30
        while len(client.app.state.rt.ingest.live.units) < 2:  # type: ignore[attr-defined]
            assert time.monotonic() < deadline, "the simulated fleet never came online"
            time.sleep(0.05)
        yield client, keys[0]


def _recv(ws: Any, timeout: float = 10.0) -> dict[str, Any]:
    """The next message, failing after `timeout` s (the test client's own receive waits
    forever, which turns a socket that went silent into a hung test)."""

    async def receive() -> Any:
        with anyio.fail_after(timeout):
            return await ws._send_rx.receive()

    message = ws.portal.call(receive)
    if message["type"] == "websocket.close":
        raise WebSocketDisconnect(message.get("code", 1000), message.get("reason", ""))
    msg: dict[str, Any] = json.loads(message["text"])
    return msg


def _until(
    ws: Any, pred: Callable[[dict[str, Any]], bool], timeout: float = 10.0
) -> list[dict[str, Any]]:
    """Messages up to and including the first that satisfies `pred` (within `timeout` s)."""
    deadline = time.monotonic() + timeout
    seen: list[dict[str, Any]] = []
    while True:
        left = deadline - time.monotonic()
        assert left > 0, f"not received in {timeout} s; got {[m['type'] for m in seen][-20:]}"
        seen.append(_recv(ws, left))
        if pred(seen[-1]):
            return seen


def _publish(client: TestClient, *marks: tuple[str, str]) -> None:
    """Publish a `live` event per (vehicle, mark) in one go on the event loop; the mark is the
    event's slot, so the test knows which of them reached it."""
    hub = client.app.state.rt.ingest.hub  # type: ignore[attr-defined]

    def publish() -> None:
        for vehicle, mark in marks:
            ref = UnitRef(vehicle, f"{vehicle}/sim", 30)
            hub.publish(Event(LIVE, ref, time.time(), {"slot": mark, "fields": {}}))

    client.portal.call(publish)  # type: ignore[union-attr]


def _marks(msgs: list[dict[str, Any]]) -> set[str]:
    return {m["data"]["slot"] for m in msgs if m["type"] == "live" and "slot" in m["data"]}


def _is_mark(mark: str) -> Callable[[dict[str, Any]], bool]:
    return lambda m: m["type"] == "live" and m["data"].get("slot") == mark


def _is_snapshot(vehicle: str) -> Callable[[dict[str, Any]], bool]:
    return lambda m: m["type"] == "snapshot" and m["vehicle_id"] == vehicle


def _is_error(m: dict[str, Any]) -> bool:
    return m["type"] == "error"


def _sync(ws: Any) -> None:
    """Wait until the server has handled every message sent before (it answers an unknown
    type with an error, in order, without changing the subscription)."""
    ws.send_json({"type": "sync-marker"})
    _until(ws, lambda m: _is_error(m) and "sync-marker" in m["reason"])


def test_unsubscribe_while_subscribed_to_all(sqlite_url: str) -> None:
    with (
        _running(sqlite_url) as (client, key),
        client.websocket_connect(f"/api/v1/ws?key={key}") as ws,
    ):
        _until(ws, _is_snapshot("SIM-002"))
        ws.send_json({"type": "unsubscribe", "vehicles": ["SIM-002"]})
        _sync(ws)
        # Published after the unsubscribe was handled, in this order: the hub's queue is FIFO,
        # so anything wanted of these arrives before `y`.
        _publish(client, ("SIM-002", "x"), ("NEW-9", "n"), ("SIM-001", "y"))
        marks = _marks(_until(ws, _is_mark("y")))
        assert "x" not in marks, "an unsubscribed vehicle kept coming"
        assert "n" in marks, "a vehicle seen after the unsubscribe must still come"


def test_subscribe_adds_and_never_narrows(sqlite_url: str) -> None:
    with _running(sqlite_url) as (client, key):
        with client.websocket_connect(f"/api/v1/ws?key={key}") as ws:
            _until(ws, _is_snapshot("SIM-002"))
            # From all, subscribing to one vehicle sends its snapshot and stays all.
            ws.send_json({"type": "subscribe", "vehicles": ["SIM-001"]})
            _until(ws, _is_snapshot("SIM-001"))
            _publish(client, ("SIM-002", "x1"), ("SIM-001", "y1"))
            assert "x1" in _marks(_until(ws, _is_mark("y1"))), "subscribe narrowed 'all'"
            # An unsubscribed vehicle comes back on subscribe, with its snapshot.
            ws.send_json({"type": "unsubscribe", "vehicles": ["SIM-002"]})
            ws.send_json({"type": "subscribe", "vehicles": ["SIM-002"]})
            _until(ws, _is_snapshot("SIM-002"))
            _publish(client, ("SIM-002", "x2"), ("NEW-9", "n2"), ("SIM-001", "y2"))
            assert {"x2", "n2"} <= _marks(_until(ws, _is_mark("y2")))
            # `*` restores all after an unsubscribe.
            ws.send_json({"type": "unsubscribe", "vehicles": ["SIM-002"]})
            ws.send_json({"type": "subscribe", "vehicles": "*"})
            _until(ws, _is_snapshot("SIM-002"))
            _publish(client, ("SIM-002", "x3"), ("SIM-001", "y3"))
            assert "x3" in _marks(_until(ws, _is_mark("y3")))
        # From a list, subscribe adds to it.
        with client.websocket_connect(f"/api/v1/ws?key={key}&vehicles=SIM-001") as ws:
            _until(ws, _is_snapshot("SIM-001"))
            ws.send_json({"type": "subscribe", "vehicles": ["SIM-002"]})
            _until(ws, _is_snapshot("SIM-002"))
            _publish(client, ("SIM-002", "x4"), ("NEW-9", "n4"), ("SIM-001", "y4"))
            marks = _marks(_until(ws, _is_mark("y4")))
            assert "x4" in marks and "n4" not in marks


def _viewer(client: TestClient, admin: str) -> tuple[int, str]:
    r = client.post(
        "/api/v1/keys",
        json={"name": "ws viewer", "role": "viewer"},
        headers={"Authorization": f"Bearer {admin}"},
    )
    assert r.status_code == 201, r.text
    return r.json()["id"], r.json()["key"]


def _closed_for_revocation(ws: Any, timeout: float) -> float:
    """Read until the error, then expect close 4401; returns how long that took."""
    start = time.monotonic()
    err = _until(ws, _is_error, timeout)[-1]
    assert "revoked" in err["reason"]
    with pytest.raises(WebSocketDisconnect) as exc:
        _until(ws, lambda m: False, 5)
    assert exc.value.code == 4401
    return time.monotonic() - start


def test_revoked_key_closes_an_open_socket(sqlite_url: str) -> None:
    with _running(sqlite_url) as (client, admin):
        key_id, key = _viewer(client, admin)
        with client.websocket_connect(
            "/api/v1/ws?vehicles=SIM-001", headers={"Authorization": f"Bearer {key}"}
        ) as ws:
            _until(ws, _is_snapshot("SIM-001"))
            # A valid key stays connected across key checks (one a second).
            until = time.monotonic() + 1.5
            while time.monotonic() < until:
                assert _recv(ws)["type"] != "error"
            r = client.delete(
                f"/api/v1/keys/{key_id}", headers={"Authorization": f"Bearer {admin}"}
            )
            assert r.status_code == 200
            # In the revoking process: within about a second (generous bound: shared cores).
            assert _closed_for_revocation(ws, timeout=10) < 5


def test_key_revoked_by_another_process_closes_within_the_cache_ttl(sqlite_url: str) -> None:
    with _running(sqlite_url, key_cache_s=0.5) as (client, admin):
        key_id, key = _viewer(client, admin)
        with client.websocket_connect(f"/api/v1/ws?key={key}&vehicles=SIM-001") as ws:
            _until(ws, _is_snapshot("SIM-001"))
            # Revoked in the database only (as `eqgw keys revoke` does from another process):
            # this process's cache is not dropped and answers until it expires.
            rt = client.app.state.rt  # type: ignore[attr-defined]
            with rt.engine.begin() as conn:
                assert q.revoke_key(conn, key_id, time.time())
            _closed_for_revocation(ws, timeout=10)


def test_binary_frame_gets_an_error_and_the_socket_stays(sqlite_url: str) -> None:
    with _running(sqlite_url) as (client, key):
        with client.websocket_connect(f"/api/v1/ws?key={key}&vehicles=SIM-001") as ws:
            _until(ws, _is_snapshot("SIM-001"))
            ws.send_bytes(b'{"type":"subscribe","vehicles":["SIM-002"]}')
            err = _until(ws, _is_error)[-1]
            assert "binary" in err["reason"]
            # Still served: a text frame is handled as ever.
            ws.send_json({"type": "subscribe", "vehicles": ["SIM-002"]})
            _until(ws, _is_snapshot("SIM-002"))
            _publish(client, ("SIM-002", "x"), ("SIM-001", "y"))
            assert "x" in _marks(_until(ws, _is_mark("y")))


# -- bounds on open websockets ------------------------------------------------------------


def _refused(ws: Any, limit: str) -> None:
    """The error naming `limit`, then close 4429."""
    err = _recv(ws)
    assert err["type"] == "error" and limit in err["reason"], err
    with pytest.raises(WebSocketDisconnect) as exc:
        _recv(ws)
    assert exc.value.code == 4429


def _refusals(client: TestClient) -> dict[str, float]:
    text = client.get("/metrics").text  # fleet-free: anyone may read it
    out = {}
    for limit in ("key", "client"):
        line = f'eqgw_ws_refused_total{{limit="{limit}"}} '
        found = [ln for ln in text.splitlines() if ln.startswith(line)]
        assert found, f"no {line.strip()} in /metrics"
        out[limit] = float(found[0].split()[-1])
    return out


def test_open_websockets_are_bounded_per_key_and_per_client(sqlite_url: str) -> None:
    """Past `ws_max_per_key` sockets of one key, or `ws_max_per_client` of one client
    address, the next is refused with an error and close code 4429, counted in /metrics;
    a socket closed frees its place."""
    with _running(sqlite_url, ws_max_per_key=2, ws_max_per_client=3) as (client, admin):
        assert _refusals(client) == {"key": 0, "client": 0}
        _, other = _viewer(client, admin)
        url = "/api/v1/ws?vehicles=SIM-001&key="
        with client.websocket_connect(url + admin) as one:
            assert _recv(one)["type"] == "snapshot"
            with client.websocket_connect(url + admin) as two:
                assert _recv(two)["type"] == "snapshot"
                with client.websocket_connect(url + admin) as three:
                    _refused(three, "this key")
                assert _refusals(client) == {"key": 1, "client": 0}
                # Another key from the same address: the address's third place.
                with client.websocket_connect(url + other) as four:
                    assert _recv(four)["type"] == "snapshot"
                    with client.websocket_connect(url + other) as five:
                        _refused(five, "this address")
                    assert _refusals(client) == {"key": 1, "client": 1}
            # `two` closed: the key has a place again (the server notices the close first).
            deadline = time.monotonic() + 10
            while True:
                with client.websocket_connect(url + admin) as again:
                    first = _recv(again)
                if first["type"] == "snapshot":
                    break
                assert time.monotonic() < deadline, "a closed socket kept its key's place"
                time.sleep(0.05)


def test_a_parked_vehicle_over_the_websocket(sqlite_url: str) -> None:
    # Ignition off: the socket says the unit is parked and the vehicle's state moved, then,
    # switched on, the unit is heard and the vehicle is ok again; a new snapshot says parked.
    keys: list[str] = []
    sim = SimulatedFleet(2, seed=1, clock=RealtimeClock(4.0))
    monitor = {"bus_silent_after_s": 4.0}
    app = create_app(
        Settings(database_url=sqlite_url, monitor=monitor),
        api=ApiSettings(),
        sim=sim,
        on_first_key=keys.append,
    )
    client = TestClient(app)
    with heap_frozen(), client:
        live = client.app.state.rt.ingest.live  # type: ignore[attr-defined]
        deadline = time.monotonic() + 30
        while len(live.units) < 2:
            assert time.monotonic() < deadline
            time.sleep(0.05)
        with client.websocket_connect(f"/api/v1/ws?key={keys[0]}&vehicles=SIM-001") as ws:
            snap = _recv(ws, 30)
            assert snap["vehicle"]["state"] == "ok" and snap["units"][0]["state"] == "online"
            client.portal.call(sim.ignition_off, "SIM-001")  # type: ignore[union-attr]
            seen: list[tuple[str, Any]] = []
            while ("vehicle_state", "parked") not in seen:
                msg = _recv_or_report(ws, client, sim, f"no parked vehicle; seen {seen}")
                if msg["type"] in ("unit_parked", "vehicle_state", "fault_open"):
                    seen.append((msg["type"], msg["data"].get("state")))
            # The unit is said parked before its vehicle is (other vehicle states may come
            # first: the socket carries every change), and no fault opens: parked, not offline.
            said = f"seen {seen}; {_monitor_report(client, sim)}"
            assert ("unit_parked", None) in seen, said
            assert seen.index(("unit_parked", None)) < seen.index(("vehicle_state", "parked")), said
            assert not [s for s in seen if s[0] == "fault_open"], said
            with client.websocket_connect(f"/api/v1/ws?key={keys[0]}&vehicles=SIM-001") as ws2:
                again = _recv(ws2, 30)
                assert again["vehicle"]["state"] == "parked"
                assert again["vehicle"]["parked_since"] and again["vehicle"]["last_heard"]
                assert again["units"][0]["state"] == "parked"
            client.portal.call(sim.ignition_on, "SIM-001")  # type: ignore[union-attr]
            kinds: list[tuple[str, Any]] = []
            while ("vehicle_state", "ok") not in kinds:
                msg = _recv_or_report(ws, client, sim, f"not ok again; seen {kinds}")
                if msg["type"] in ("unit_online", "vehicle_state"):
                    kinds.append((msg["type"], msg["data"].get("state")))
            said = f"seen {kinds}; {_monitor_report(client, sim)}"
            assert ("unit_online", None) in kinds, said
            assert kinds.index(("unit_online", None)) < kinds.index(("vehicle_state", "ok")), said


def _recv_or_report(ws: Any, client: TestClient, sim: SimulatedFleet, what: str) -> dict[str, Any]:
    """The next message within 30 s; else a failure saying `what` and what the monitors know."""
    try:
        return _recv(ws, 30)
    except TimeoutError:
        raise AssertionError(f"{what} in 30 s; {_monitor_report(client, sim)}") from None


def _monitor_report(client: TestClient, sim: SimulatedFleet) -> str:
    """What the gateway's monitors know (a failed wait for a state says why it never came)."""
    rt = client.app.state.rt  # type: ignore[attr-defined]
    pipeline = rt.ingest.pipeline
    parts = [f"pipeline clock {pipeline.clock:.3f}, sim now {sim.clock.now():.3f}"]
    parts.append(f"sim error {sim.error!r}")
    for name, b in pipeline.bindings.items():
        act = b.activity
        parts.append(f"bus {name}: heard {act.heard:.3f} active_since {act.active_since:.3f}")
    for key, st in pipeline.live.units.items():
        f = st.faults
        parts.append(
            f"unit {key}: last frame {f._last_frame} parked {f.parked_since}"
            f" open {sorted(f.open)} awaiting {f._awaiting_bus} watch {f._watch_from}"
        )
    return "; ".join(parts)


# -- protocol 2: what changed --------------------------------------------------------------


def test_protocol_2_sends_what_changed_with_the_diagnosis(sqlite_url: str) -> None:
    """`?v=2`: a live slot's second value comes as the fields that changed, the diagnosis
    only when it changed; a field gone sends the slot whole; status changes as the flags
    that changed (whole the first time). A protocol 1 client on the same events gets every
    value whole."""
    with (
        _running(sqlite_url) as (client, key),
        client.websocket_connect(f"/api/v1/ws?key={key}&vehicles=SIM-001&v=2") as ws,
        client.websocket_connect(f"/api/v1/ws?key={key}&vehicles=SIM-001") as old,
    ):
        snap = _until(ws, _is_snapshot("SIM-001"))[-1]
        assert snap["units"] and all(u["diagnosis"]["condition"] for u in snap["units"])
        assert _until(old, _is_snapshot("SIM-001"))[-1]["units"][0]["diagnosis"]
        hub = client.app.state.rt.ingest.hub  # type: ignore[attr-defined]
        # A unit of its own (SA 99: the simulator's never send), so only these events count.
        ref = UnitRef("SIM-001", "SIM-001/sim", 99)
        a = {"v12": 12.0, "v24": 24.07, "i12": 1.0}  # B - A 0.07 V: normal
        b = {"v12": 12.0, "v24": 24.3, "i12": 1.0}  # 0.3 V, not running: not functioning
        c = {"v12": 12.0, "v24": 24.3, "i12": 2.0}
        d = {"v12": 12.0, "v24": 24.3}  # i12 gone
        flags1 = {"eqrn": "active", "eqflt": "inactive"}  # running: overload
        flags2 = {"eqrn": "active", "eqflt": "active"}

        def publish() -> None:
            for i, f in enumerate((a, b, c, d)):
                hub.publish(Event(LIVE, ref, 100.0 + i, {"slot": "voltages", "fields": f}))
            for i, f in enumerate((flags1, flags2)):
                data = {"flags": f, "changed": sorted(f)}
                hub.publish(Event(STATUS_CHANGE, ref, 110.0 + i, data))
            hub.publish(Event(LIVE, ref, 120.0, {"slot": "end", "fields": {}}))

        client.portal.call(publish)  # type: ignore[union-attr]

        def ours(msgs: list[dict[str, Any]]) -> list[dict[str, Any]]:
            return [m["data"] for m in msgs if m["unit"] == 99 and m["vehicle_id"] == "SIM-001"]

        got = ours(_until(ws, _is_mark("end")))
        assert got == [
            {
                "slot": "voltages",
                "fields": a,
                "diagnosis": {"condition": "normal", "text": got[0]["diagnosis"]["text"]},
            },
            {
                "slot": "voltages",
                "changed": {"v24": 24.3},
                "diagnosis": {
                    "condition": "equalizer_not_functioning",
                    "text": got[1]["diagnosis"]["text"],
                },
            },
            {"slot": "voltages", "changed": {"i12": 2.0}},
            {"slot": "voltages", "fields": d},
            {
                "flags": flags1,
                "diagnosis": {"condition": "overload", "text": got[4]["diagnosis"]["text"]},
            },
            {"changed": {"eqflt": "active"}},
            {"slot": "end", "fields": {}},
        ]
        assert "0.10 V" in got[1]["diagnosis"]["text"]
        whole = ours(_until(old, _is_mark("end")))
        assert [m["fields"] if "fields" in m else m["flags"] for m in whole] == [
            a,
            b,
            c,
            d,
            flags1,
            flags2,
            {},
        ]


def _merged(state: dict[tuple[int, str], dict[str, Any]], msg: dict[str, Any]) -> None:
    """Apply one message to {(unit, slot): fields} as a client does."""
    if msg["type"] == "snapshot":
        for u in msg["units"]:
            for slot, v in u["latest"].items():
                state[(u["sa"], slot)] = dict(v["fields"])
    elif msg["type"] == "live":
        key = (msg["unit"], msg["data"]["slot"])
        if "fields" in msg["data"]:
            state[key] = dict(msg["data"]["fields"])
        else:
            state[key].update(msg["data"]["changed"])
    elif msg["type"] == "status_change":  # the flags are the `status` slot (docs/api.md)
        key = (msg["unit"], "status")
        if "flags" in msg["data"]:
            state[key] = dict(msg["data"]["flags"])
        else:
            state[key].update(msg["data"]["changed"])


def test_protocol_2_merged_is_what_protocol_1_sends_whole(sqlite_url: str) -> None:
    """The simulator streaming: a protocol 2 client that merges each change into its
    snapshot holds, slot for slot, what a protocol 1 client holds from whole values."""
    with (
        _running(sqlite_url) as (client, key),
        client.websocket_connect(f"/api/v1/ws?key={key}&vehicles=SIM-001&v=2") as ws,
        client.websocket_connect(f"/api/v1/ws?key={key}&vehicles=SIM-001") as old,
    ):
        time.sleep(1.0)  # events of the simulator's units while both are open
        _publish(client, ("SIM-001", "end"))
        states: list[dict[tuple[int, str], dict[str, Any]]] = []
        deltas = 0
        for sock in (ws, old):
            state: dict[tuple[int, str], dict[str, Any]] = {}
            msgs = _until(sock, _is_mark("end"))
            for m in msgs:
                _merged(state, m)
            deltas += sum(1 for m in msgs if m["type"] == "live" and "changed" in m["data"])
            states.append(state)
        assert deltas, "no value came as a change"
        # Slots the two snapshots (taken moments apart) agree on or an event set since.
        assert states[0] == states[1]


def test_unknown_protocol_version_is_refused(sqlite_url: str) -> None:
    with _running(sqlite_url) as (client, key):
        with client.websocket_connect(f"/api/v1/ws?key={key}&v=3") as ws:
            with pytest.raises(WebSocketDisconnect) as exc:
                _recv(ws)
            assert exc.value.code == 1003


def test_protocol_2_status_flags_are_the_status_slot() -> None:
    """A `status_change` and a `live` message of slot `status` update the same slot: each is
    sent as the flags changed since the last of both (what docs/api.md tells a client)."""
    from eqgw.api.ws import _Sent

    sent = _Sent()
    ref = UnitRef("V1", "V1/can0", 30)
    flags = {"eq_state_on": "active", "fault_low_v": "inactive"}
    first = json.loads(sent.message(Event(STATUS_CHANGE, ref, 1.0, {"flags": flags})))
    assert first["data"]["flags"] == flags  # the first: whole
    later = {"eq_state_on": "active", "fault_low_v": "active"}
    live = json.loads(sent.message(Event(LIVE, ref, 2.0, {"slot": "status", "fields": later})))
    assert live["data"]["slot"] == "status" and live["data"]["changed"] == {"fault_low_v": "active"}
    back = json.loads(sent.message(Event(STATUS_CHANGE, ref, 3.0, {"flags": flags})))
    assert back["data"]["changed"] == {"fault_low_v": "inactive"}
