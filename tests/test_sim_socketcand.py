"""`eqgw simulate` in its own process, opened by name with python-can's socketcand interface;
the frames are decoded by FrameDecoder, and its BAM DM1s identically by pretty_j1939."""

from __future__ import annotations

import os
import queue
import re
import signal
import subprocess
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import can
import pytest

from eqgw.protocol.decode import FrameDecoder
from eqgw.protocol.encode import encode
from eqgw.protocol.j1939 import PGN_COMPONENT_ID, PGN_DM1, PGN_TP_CM, PGN_TP_DT, pgn_of
from eqgw.protocol.records import Record
from tests.proc_helpers import eqgw, popen, run

REPO = Path(__file__).resolve().parent.parent
SCENARIO = """
vehicles:
  - name: XP-1
    units: [{sa: 30, series: 80, rating: 100}]
    alternator: true
    alternator_v: 31.0
    load_12v: 20
events:
  - {at: 0, vehicle: XP-1, action: fail_equalizer}
"""


class Simulator:
    """A running `eqgw simulate` subprocess and the lines it printed."""

    def __init__(self, args: list[str]) -> None:
        self.proc = popen(eqgw("simulate", *args), REPO, dict(os.environ), stderr_apart=True)
        self.lines: queue.Queue[str] = queue.Queue()
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            self.lines.put(line.rstrip("\n"))

    def port(self, timeout: float = 30.0) -> int:
        line = self.lines.get(timeout=timeout)
        match = re.fullmatch(r"listening 127\.0\.0\.1:(\d+)", line)
        assert match, line
        return int(match.group(1))

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)
            try:
                self.proc.wait(timeout=15)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(timeout=5)
        self._reader.join(timeout=5)
        for stream in (self.proc.stdout, self.proc.stderr):
            if stream is not None:
                stream.close()


@pytest.fixture
def simulator(tmp_path: Path) -> Iterator[Simulator]:
    scenario = tmp_path / "xp.yaml"
    scenario.write_text(SCENARIO)
    sim = Simulator(
        [
            "--vehicles", "3", "--listen", "127.0.0.1:0", "--speed", "10",
            "--seed", "1", "--scenario", str(scenario), "--background-traffic",
        ]
    )  # fmt: skip
    try:
        yield sim
    finally:
        sim.stop()


def pretty_dm1s(frames: list[can.Message]) -> list[dict[str, Any]]:
    """DM1s with DTCs as pretty_j1939 describes them, frame by frame."""
    from pretty_j1939.describe import get_describer

    describer = get_describer(include_na=True)
    out = []
    for msg in frames:
        description = describer(bytes(msg.data), msg.arbitration_id)
        if description.get("_pgn") != PGN_DM1:
            continue
        dtcs = []
        for key in sorted(
            (k for k in description if k.startswith("DTC ")), key=lambda k: int(k[4:])
        ):
            m = re.match(r"^SPN (\d+) \(.*\), FMI (\d+), OC (\d+)", description[key])
            assert m, description[key]
            spn, fmi, oc = (int(g) for g in m.groups())
            dtcs.append({"spn": spn, "fmi": fmi, "oc": oc})
        if dtcs:
            lamp = description["Amber Warning Lamp Status"]
            out.append({"awl": ["Off", "On", "Error", "Not Available"].index(lamp), "dtcs": dtcs})
    return out


def test_simulate_serves_buses_over_socketcand(simulator: Simulator) -> None:
    port = simulator.port()
    banner = [simulator.lines.get(timeout=10) for _ in range(4)]
    assert "3 buses over socketcand" in banner[0]
    assert banner[1].split()[:4] == ["XP-1", "80-series", "SA", "30"]
    assert banner[2].split()[0] == "SIM-001" and banner[3].split()[0] == "SIM-002"

    bus = can.Bus(interface="socketcand", host="127.0.0.1", port=port, channel="XP-1")
    decoder = FrameDecoder(equalizer_sas=(30,))
    frames: list[can.Message] = []
    records: list[Record] = []
    try:
        deadline = time.monotonic() + 60.0
        while not frames and time.monotonic() < deadline:
            msg = bus.recv(timeout=0.5)
            if msg is not None:
                frames.append(msg)
        # The first frame proves rawmode is up: now a request reaches the unit and back.
        for can_id, data in encode(
            "request", {"requested_pgn": PGN_COMPONENT_ID, "da": 30}, sa=0xD8
        ):
            bus.send(can.Message(arbitration_id=can_id, data=data, is_extended_id=True))

        def have(name: str, predicate: Any = None) -> bool:
            return any(r.name == name and (predicate is None or predicate(r)) for r in records)

        while time.monotonic() < deadline:
            msg = bus.recv(timeout=0.5)
            if msg is None:
                continue
            frames.append(msg)
            records.extend(decoder.decode_message(msg))
            if (
                have("component_id")
                and all(have(n) for n in ("status", "heartbeat", "voltages", "battery_states"))
                and sum(1 for r in records if r.name == "dm1" and len(r.fields["dtcs"]) > 1) >= 2
            ):
                break
    finally:
        bus.shutdown()

    assert [r.fields["text"] for r in records if r.name == "component_id"] == ["EQ8001"]
    volts = next(r for r in records if r.name == "voltages").fields
    assert volts["v24"] == pytest.approx(31.0, abs=0.05)
    bam_dm1 = [r for r in records if r.name == "dm1" and len(r.fields["dtcs"]) > 1]
    assert len(bam_dm1) >= 2, [r for r in records if r.name == "dm1"]
    codes = {d["code"] for d in bam_dm1[-1].fields["dtcs"]}
    assert {"OVF", "EQFLT"} <= codes
    assert any(pgn_of(m.arbitration_id) == PGN_TP_CM for m in frames)
    # Other nodes' traffic is there and is not taken for equalizer data.
    assert any(m.arbitration_id & 0xFF == 0x00 for m in frames)
    assert all(r.sa == 30 for r in records)

    # pretty_j1939 reads the same DM1s from the same frames.
    dm1_frames = [
        m
        for m in frames
        if m.arbitration_id & 0xFF == 30
        and pgn_of(m.arbitration_id) in (PGN_DM1, PGN_TP_CM, PGN_TP_DT)
    ]
    theirs = pretty_dm1s(dm1_frames)
    ours = [
        {
            "awl": r.fields["lamps"]["awl"],
            "dtcs": [{k: d[k] for k in ("spn", "fmi", "oc")} for d in r.fields["dtcs"]],
        }
        for r in records
        if r.name == "dm1" and r.fields["dtcs"]
    ]
    assert theirs == ours


def test_unknown_scenario_is_an_error() -> None:
    proc = run(eqgw("simulate", "--scenario", "no-such-thing"), REPO, dict(os.environ), timeout=60)
    assert proc.returncode == 2
    assert "no-such-thing" in proc.stderr


def test_list_scenarios() -> None:
    proc = run(eqgw("simulate", "--list-scenarios"), REPO, dict(os.environ), timeout=60)
    assert proc.returncode == 0
    assert "night-undervoltage" in proc.stdout


def test_duration_runs_every_vehicle_to_exactly_the_end(tmp_path: Path) -> None:
    """`--duration` ends the run when every vehicle has been simulated up to that many
    simulated seconds, however far the real-time steps fall behind at a high speed: the
    recording covers the whole span and nothing past it, and the exit is 0."""
    duration, speed = 3600.0, 20000.0
    proc = run(
        eqgw(
            "simulate",
            "--vehicles",
            "3",
            "--seed",
            "5",
            "--speed",
            str(speed),
            "--duration",
            str(duration),
            "--listen",
            "127.0.0.1:0",
            "--record",
            str(tmp_path),
        ),
        REPO,
        dict(os.environ),
        timeout=120,
    )
    assert proc.returncode == 0, proc.stderr
    logs = sorted(tmp_path.glob("*.log"))
    assert len(logs) == 3
    for log in logs:
        stamps = [m.timestamp for m in can.LogReader(str(log))]
        assert stamps, log
        first, last = stamps[0], stamps[-1]
        # Voltages and status come every 3 s: the last frames are within one period of the end.
        assert duration - 3.5 <= last - first <= duration + 1e-6, (log.name, last - first)
