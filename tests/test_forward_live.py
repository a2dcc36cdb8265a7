"""Edge-forwarded vehicles in the central's live view: the real app in process (SQLite and
PostgreSQL), a simulated vehicle's frames uploaded with an ingest key, read back with a viewer
key from `/vehicles`, `/vehicles/{id}/live` and the websocket snapshot; offline once the
uploads stop, with the last frame's time; restored after a restart, online again on upload."""

from __future__ import annotations

import json
import time
import warnings
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

import can

with warnings.catch_warnings():
    # Starlette wants httpx2 for its test client; httpx works and is what is installed.
    warnings.simplefilter("ignore")
    from starlette.testclient import TestClient

from eqgw.config import AlertSettings, Settings, VehicleConfig
from eqgw.forward.protocol import flags_of
from eqgw.ingest.state import live_key
from eqgw.main import create_app
from eqgw.protocol.decode import FrameDecoder
from eqgw.protocol.encode import encode
from eqgw.protocol.j1939 import PGN_COMPONENT_ID, PGN_SOFTWARE_ID
from eqgw.security.keys import create_key
from eqgw.store.engine import create_engine
from eqgw.store.migrate import upgrade_engine
from eqgw.web.settings import ApiSettings
from tests.api_helpers import heap_frozen
from tests.forward_helpers import VEHICLE, RecordedVehicle
from tests.proc_helpers import wait_until
from tests.test_api_ws import _recv

BUS = f"{VEHICLE}/can0"
OFFLINE_AFTER_S = 10.0  # the monitor's default


def _keys(db_url: str) -> dict[str, str]:
    engine = create_engine(db_url)
    try:
        upgrade_engine(engine)
        roles = ("admin", "operator", "viewer", "ingest")
        return {role: create_key(engine, role, role)[1] for role in roles}
    finally:
        engine.dispose()


@contextmanager
def _central(db_url: str) -> Iterator[TestClient]:
    settings = Settings(
        database_url=db_url,
        vehicles=[VehicleConfig(id=VEHICLE, name="Bus 1", depot="north")],
        alerts=AlertSettings(enabled=False),
    )
    # Listings rendered fresh: the test reads right after each upload.
    with heap_frozen(), TestClient(create_app(settings, api=ApiSettings(live_cache_s=0))) as client:
        yield client


def _drive(veh: RecordedVehicle, seconds: float) -> list[can.Message]:
    """Simulated seconds of the vehicle; the frames its units sent meanwhile."""
    before = len(veh.kept())
    for _ in range(int(seconds / 5)):
        veh.fleet.advance(5.0)
    return veh.kept()[before:]


def _identify(veh: RecordedVehicle) -> None:
    """Ask each unit for its IDs on its bus (as a tool on the vehicle might): the answers are
    among the frames the forwarder uploads."""
    with can.Bus(interface="virtual", channel=veh.channel) as bus:
        for sa in veh.sas:
            for pgn in (PGN_COMPONENT_ID, PGN_SOFTWARE_ID):
                for can_id, data in encode("request", {"requested_pgn": pgn, "da": sa}, sa=0xF9):
                    bus.send(can.Message(arbitration_id=can_id, data=data, is_extended_id=True))
    veh.fleet.poll()


def _shifted(msgs: list[can.Message], shift: float) -> list[can.Message]:
    for m in msgs:
        m.timestamp += shift
    return msgs


def _upload(
    client: TestClient, key: str, msgs: list[can.Message], first_seq: int, sas: list[int]
) -> int:
    """Post `msgs` as a forwarder would, in two batches; returns the next sequence number."""
    half = len(msgs) // 2
    seq = first_seq
    for part in (msgs[:half], msgs[half:]):
        body = {
            "stream": "live-test",
            "vehicle": VEHICLE,
            "bus": BUS,
            "equalizer_sas": sas,
            "first_seq": seq,
            "frames": [
                [m.timestamp, m.arbitration_id, bytes(m.data).hex(), flags_of(m)] for m in part
            ],
        }
        r = client.post(
            "/api/v1/ingest/frames", json=body, headers={"Authorization": f"Bearer {key}"}
        )
        assert r.status_code == 200, r.text
        assert r.json()["stored"] == len(part)
        seq += len(part)
    return seq


class Expected:
    """What the live view must show: the frames decoded here, the latest record per slot."""

    def __init__(self, sas: list[int]) -> None:
        self.decoder = FrameDecoder(tuple(sas))
        self.latest: dict[int, dict[str, dict[str, Any]]] = {sa: {} for sa in sas}
        self.last_seen: dict[int, float] = {}

    def add(self, msgs: list[can.Message]) -> None:
        for m in msgs:
            for rec in self.decoder.decode(
                m.timestamp, BUS, m.arbitration_id, bytes(m.data), is_extended=m.is_extended_id
            ):
                slot = live_key(rec.name, rec.fields)
                # JSON round trip: what the API answers (tuples become lists).
                fields = json.loads(json.dumps(rec.fields))
                if rec.name == "request":  # to a unit: its slot, not its last seen
                    self.latest[rec.fields["da"]][slot] = {"ts": rec.ts, "fields": fields}
                    continue
                self.latest[rec.sa][slot] = {"ts": rec.ts, "fields": fields}
                self.last_seen[rec.sa] = max(self.last_seen.get(rec.sa, rec.ts), rec.ts)

    def voltages(self, sa: int) -> dict[str, Any]:
        fields: dict[str, Any] = self.latest[sa]["voltages"]["fields"]
        return fields


def _get(client: TestClient, key: str, path: str) -> Any:
    r = client.get(f"/api/v1{path}", headers={"Authorization": f"Bearer {key}"})
    assert r.status_code == 200, r.text
    return r.json()


def _vehicle(client: TestClient, key: str) -> dict[str, Any]:
    listing = _get(client, key, "/vehicles")
    [v] = [v for v in listing["vehicles"] if v["id"] == VEHICLE]
    return dict(v)


def _snapshot(client: TestClient, key: str) -> dict[str, Any]:
    with client.websocket_connect(f"/api/v1/ws?key={key}&vehicles={VEHICLE}") as ws:
        snap = _recv(ws)  # bounded: a silent socket fails, never hangs
    assert snap["type"] == "snapshot" and snap["vehicle_id"] == VEHICLE
    return snap


def _check_values(client: TestClient, key: str, exp: Expected, *, online: bool) -> None:
    """The listing, the vehicle's live view and the websocket snapshot all show `exp`."""
    sas = sorted(exp.latest)
    v = _vehicle(client, key)
    assert (v["name"], v["depot"], v["online"]) == ("Bus 1", "north", online)
    assert [u["unit"] for u in v["units"]] == sas
    for u in v["units"]:
        sa = u["unit"]
        volts, model = exp.voltages(sa), exp.latest[sa]["component_id"]["fields"]["text"]
        assert (u["bus"], u["online"], u["last_seen"]) == (BUS, online, exp.last_seen[sa])
        assert (u["v12"], u["v24"]) == (volts["v12"], volts["v24"])
        assert (u["series"], u["model"]) == (80, model)
        assert "OFFLINE" not in u["active_faults"]  # out of range is not a unit fault
        assert u["diagnosis"]["condition"]
    live = _get(client, key, f"/vehicles/{VEHICLE}/live")
    assert [u["unit"] for u in live["units"]] == sas
    for u in live["units"]:
        sa = u["unit"]
        assert u["latest"] == exp.latest[sa]
        assert u["status_flags"] == exp.latest[sa]["status"]["fields"]
        assert (u["online"], u["last_seen"], u["summary"]["online"]) == (
            online, exp.last_seen[sa], online,
        )  # fmt: skip
        assert u["series"] == 80 and u["software_id"]
        assert u["diagnosis"]["battery_a_v"] == exp.voltages(sa)["v12"]
    snap = _snapshot(client, key)
    assert [u["sa"] for u in snap["units"]] == sas
    for u in snap["units"]:
        assert u["latest"] == exp.latest[u["sa"]]
        assert (u["online"], u["last_seen"]) == (online, exp.last_seen[u["sa"]])


def test_forwarded_vehicle_live_offline_and_after_a_restart(db_url: str) -> None:
    keys = _keys(db_url)
    veh = RecordedVehicle(pick=3)  # two 80-series units in parallel, SA 30 and 31
    assert veh.sas == [30, 31]
    veh.fleet.open()
    try:
        veh.fleet.advance(1.0)
        _identify(veh)
        _drive(veh, 40)
        first = veh.kept()
        exp = Expected(veh.sas)
        with _central(db_url) as client:
            # Nothing forwarded yet: the configured vehicle has no units.
            assert _vehicle(client, keys["viewer"])["units"] == []
            # The vehicle's frames up to a second ago (its clock: the frames' stamps).
            shift = time.time() - 1.0 - first[-1].timestamp
            exp.add(_shifted(first, shift))
            seq = _upload(client, keys["ingest"], first, 1, veh.sas)
            _check_values(client, keys["viewer"], exp, online=True)

            # The forwarder falls silent (out of range): offline once its last frame is
            # older than offline_after_s, still showing what was last heard and when.
            def offline() -> bool:
                return not _vehicle(client, keys["viewer"])["online"]

            wait_until(offline, 6 * OFFLINE_AFTER_S, "the silent vehicle to show offline")
            assert time.time() - exp.last_seen[30] > OFFLINE_AFTER_S
            _check_values(client, keys["viewer"], exp, online=False)

        # A central restart: before any upload the vehicle is back in the live view, as it
        # was acknowledged, and offline.
        with _central(db_url) as client:
            _check_values(client, keys["viewer"], exp, online=False)
            # Back in range after a while (the vehicle was off meanwhile: a gap in its
            # frames): online again with the new values.
            second = _drive(veh, 20)
            gap_shift = time.time() - 1.0 - second[-1].timestamp
            exp.add(_shifted(second, gap_shift))
            _upload(client, keys["ingest"], second, seq, veh.sas)
            _check_values(client, keys["viewer"], exp, online=True)
            # Shown, but the central has no way onto the vehicle's bus: commands are refused.
            r = client.post(
                f"/api/v1/vehicles/{VEHICLE}/commands",
                json={"unit": 30, "jump_start_override": True},
                headers={"Authorization": f"Bearer {keys['operator']}"},
            )
            assert (r.status_code, r.json()["type"]) == (409, "no_bus"), r.text
    finally:
        veh.fleet.close()


def test_late_upload_of_old_frames_is_not_online(sqlite_url: str) -> None:
    """A backlog uploaded now (frames an hour old) fills the live view but is not live."""
    keys = _keys(sqlite_url)
    veh = RecordedVehicle(pick=3)
    veh.fleet.open()
    try:
        veh.fleet.advance(1.0)
        _identify(veh)
        _drive(veh, 30)
        frames = veh.kept()
        exp = Expected(veh.sas)
        exp.add(_shifted(frames, time.time() - 3600.0 - frames[-1].timestamp))
        with _central(sqlite_url) as client:
            _upload(client, keys["ingest"], frames, 1, veh.sas)
            _check_values(client, keys["viewer"], exp, online=False)
            assert time.time() - max(exp.last_seen.values()) > 3000
    finally:
        veh.fleet.close()


def test_alert_rules_evaluate_forwarded_units(sqlite_url: str) -> None:
    keys = _keys(sqlite_url)
    veh = RecordedVehicle(pick=1)
    sas = veh.sas
    settings = Settings(
        database_url=sqlite_url,
        vehicles=[VehicleConfig(id=VEHICLE, name="Bus 1", depot="north")],
    )  # alerting on, as by default

    def alerts(state: str) -> list[dict[str, Any]]:
        listing = _get(client, keys["viewer"], f"/alerts?vehicle={VEHICLE}&state={state}")
        return [a for a in listing["alerts"] if a["rule"] == "equalizer_fault"]

    veh.fleet.open()
    try:
        with (
            heap_frozen(),
            TestClient(create_app(settings, api=ApiSettings(live_cache_s=0))) as client,
        ):
            veh.fleet.advance(1.0)
            seq = _upload(client, keys["ingest"], _drive(veh, 20), 1, sas)
            assert alerts("open") == []
            veh.fleet.fail_equalizer(veh.name)
            seq = _upload(client, keys["ingest"], _drive(veh, 30), seq, sas)
            [raised] = wait_until(lambda: alerts("open"), 60, "equalizer_fault on the upload")
            assert (raised["vehicle_id"], raised["bus"], raised["sa"]) == (VEHICLE, BUS, sas[0])
            assert raised["severity"] == "critical"
            veh.fleet.restore_equalizer(veh.name)
            _upload(client, keys["ingest"], _drive(veh, 30), seq, sas)
            wait_until(lambda: not alerts("open"), 60, "the alert to clear on the next upload")
            [cleared] = alerts("cleared")
            assert cleared["id"] == raised["id"]
    finally:
        veh.fleet.close()
