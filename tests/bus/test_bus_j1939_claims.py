"""A unit is its J1939 NAME where address claims are seen: when a node with a lower NAME takes
the equalizer's address from an independent J1939 stack's node (can-j1939) holding it, the old
unit's data ends (its open faults close, its live values go) and the new owner's frames start
a new unit; the change is recorded. Frames come off a python-can virtual bus into the ingest
pipeline as the gateway reads them."""

from __future__ import annotations

from collections.abc import Iterator

import can
import j1939
import pytest

from eqgw.ingest.pipeline import BusBinding, IngestPipeline
from eqgw.ingest.rows import EpisodeRow, MessageRow
from eqgw.protocol.claims import ClaimTracker
from eqgw.protocol.encode import encode
from tests.bus_helpers import wait_for
from tests.j1939_helpers import Observer, stack_name

UNIT = 0x1E
CLAIMED = j1939.ControllerApplication.State.NORMAL
CANNOT = j1939.ControllerApplication.State.CANNOT_CLAIM


@pytest.fixture
def ecus(channel: str) -> Iterator[tuple[j1939.ElectronicControlUnit, ...]]:
    units = tuple(j1939.ElectronicControlUnit() for _ in range(2))
    for u in units:
        u.connect(interface="virtual", channel=channel)
    yield units
    for u in units:
        u.disconnect()
        u.stop()


def _send(bus: can.BusABC, frames: list[tuple[int, bytes]]) -> None:
    for can_id, data in frames:
        bus.send(can.Message(arbitration_id=can_id, data=data, is_extended_id=True))


async def test_a_new_owner_of_the_units_address_ends_the_old_units_data(
    channel: str, ecus: tuple[j1939.ElectronicControlUnit, ...]
) -> None:
    observer = Observer(channel)
    unit_tx = can.Bus(interface="virtual", channel=channel)  # the unit's application frames
    try:
        old_name, new_name = stack_name(1, 130, 7), stack_name(0, 0, 3)  # new: lower, wins
        old = j1939.ControllerApplication(old_name, UNIT)
        ecus[0].add_ca(controller_application=old)
        old.start()
        await wait_for(lambda: old.state == CLAIMED, "the unit's claim")
        # The unit reports an imbalance fault, then its status.
        dm1 = {"lamps": {"mil": 0, "rsl": 0, "awl": 1, "pl": 0},
               "dtcs": [{"spn": 520448, "fmi": 0, "oc": 1, "cm": 0}]}  # fmt: skip
        _send(unit_tx, encode("dm1", dm1, sa=UNIT) + encode("status", {}, sa=UNIT))
        new = j1939.ControllerApplication(new_name, UNIT)
        ecus[1].add_ca(controller_application=new)
        new.start()
        await wait_for(lambda: old.state == CANNOT and new.state == CLAIMED, "the takeover")
        _send(unit_tx, encode("heartbeat", {"heartbeat": 1}, sa=UNIT))  # the new node's

        def heartbeat_seen() -> bool:
            return any(m.arbitration_id & 0xFFFF00 == 0xFFD500 for m in observer.drain())

        await wait_for(heartbeat_seen, "the new node's frame")

        pipeline = IngestPipeline([BusBinding("BUS-101/can0", "BUS-101", (UNIT,))])
        for msg in observer.drain():
            msg.channel = "BUS-101/can0"
            pipeline.process(msg)
        rows = pipeline.take_rows()
        closed = [r.values for r in rows if isinstance(r, EpisodeRow) and r.values["ended_by"]]
        assert [(r["fault"], r["ended_by"]) for r in closed] == [("IMB", "address_lost")]
        st = pipeline.live.units[("BUS-101/can0", UNIT)]
        claim = st.latest["address_claim"][1]
        assert claim == {
            "name": f"0x{new_name.value:016X}",
            "previous_name": f"0x{old_name.value:016X}",
            "owner_changed": True,
        }
        # The old unit's values are gone from the unit; the new node's are there.
        assert "dm1" not in st.latest and "status" not in st.latest
        assert "heartbeat" in st.latest and not st.faults.open
        claims = [r.values for r in rows if isinstance(r, MessageRow)]
        messages = [m for m in claims if m["name"] == "address_claim"]
        assert [m["fields"]["owner_changed"] for m in messages] == [False, True]
    finally:
        observer.bus.shutdown()
        unit_tx.shutdown()


def _claim(name: int, address: int) -> tuple[int, bytes]:
    return 0x18EEFF00 | address, name.to_bytes(8, "little")


def test_tracker_contention_rules() -> None:
    t = ClaimTracker(defend_s=0.5)
    (first,) = t.observe(0.0, *_claim(100, UNIT))
    assert (first.previous, first.name) == (None, 100)
    assert t.observe(1.0, *_claim(200, UNIT)) == []  # a higher NAME challenges...
    assert t.observe(1.1, *_claim(100, UNIT)) == []  # ...and the owner defends
    assert t.tick(5.0) == [] and t.owner(UNIT) == 100
    assert t.observe(6.0, *_claim(200, UNIT)) == []  # challenged, not defended in time:
    (taken,) = t.tick(6.6)  # the owner is gone (a unit replaced while off the bus)
    assert (taken.previous, taken.name, taken.ts) == (100, 200, 6.0)
    (lower,) = t.observe(7.0, *_claim(50, UNIT))  # a lower NAME takes it at once
    assert (lower.previous, lower.name) == (200, 50)
    assert t.observe(7.1, *_claim(200, 0xFE)) == []  # the loser's "cannot claim"
    assert t.observe(8.0, *_claim(50, 0xFE)) == [] and t.owner(UNIT) is None  # gave it up
    assert t.observe(9.0, *_claim(50, UNIT)) == []  # the same node again: no change
    (after,) = t.observe(10.0, *_claim(30, UNIT))
    assert (after.previous, after.name) == (50, 30)


def _restored(live: dict[str, tuple[float, dict[str, object]]]) -> IngestPipeline:
    pipeline = IngestPipeline([BusBinding("BUS-101/can0", "BUS-101", (UNIT,))])
    row = {"bus": "BUS-101/can0", "sa": UNIT, "series": 80, "model": "EQ8001",
           "software_id": None, "first_seen": 0.5, "last_seen": 3.0, "live": live,
           "episodes": []}  # fmt: skip
    assert pipeline.restore([row]) == 1
    return pipeline


def test_a_restart_keeps_the_name_and_not_the_previous_owners_values() -> None:
    dm1 = (1.0, {"lamps": {}, "dtcs": []})
    changed = {"name": "0x0000000000000003", "previous_name": "0x10", "owner_changed": True}
    pipeline = _restored({"dm1": dm1, "address_claim": (2.0, changed), "heartbeat": (3.0, {})})
    st = pipeline.live.units[("BUS-101/can0", UNIT)]
    assert sorted(st.latest) == ["address_claim", "heartbeat"]
    # A NAME known from before the restart: another NAME claiming the address is a new owner.
    known = {"name": "0x0000000000000064", "previous_name": None, "owner_changed": False}
    pipeline = _restored({"address_claim": (2.0, known), "heartbeat": (3.0, {})})
    msg = can.Message(
        timestamp=10.0, arbitration_id=0x18EEFF1E, data=(200).to_bytes(8, "little"),
        channel="BUS-101/can0",
    )  # fmt: skip
    pipeline.process(msg)
    st = pipeline.live.units[("BUS-101/can0", UNIT)]
    assert st.latest["address_claim"][1] == {
        "name": "0x00000000000000C8",
        "previous_name": "0x0000000000000064",
        "owner_changed": True,
    }
    assert "heartbeat" not in st.latest and st.series is None
