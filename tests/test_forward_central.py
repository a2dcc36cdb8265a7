"""The central side of forwarding without HTTP: two central instances on one database taking
the same stream (several gateways behind one address) still decode each frame once."""

from __future__ import annotations

import time

from sqlalchemy import Engine, select

from eqgw.config import Settings, VehicleConfig
from eqgw.forward.central import ForwardIngest, Upload
from eqgw.store.archive import count_frames
from eqgw.store.forward_models import ForwardStream

T0 = time.time()


def _upload(first: int, last: int) -> Upload:
    frames = [(T0 + i, 0x18FFD61E, "d809b013ba7cc87d", 1) for i in range(first, last + 1)]
    return Upload("s1", "VAN-1", "VAN-1/can0", (30,), first, frames)


async def test_two_central_instances_share_a_stream(engine: Engine, db_url: str) -> None:
    settings = Settings(database_url=db_url, vehicles=[VehicleConfig(id="VAN-1")])
    a = ForwardIngest(settings, engine)
    b = ForwardIngest(settings, engine)
    assert (await b.take(_upload(1, 50)))["acked_seq"] == 50
    # A learns the stream from the database and stores only what is new.
    assert await a.take(_upload(1, 100)) == {
        "stream": "s1", "acked_seq": 100, "stored": 50, "duplicates": 50,
        "refused": 0, "refused_reasons": {},
    }  # fmt: skip
    # B still believes 50: its commit finds the row moved on, and it starts over from there.
    assert await b.take(_upload(51, 150)) == {
        "stream": "s1", "acked_seq": 150, "stored": 50, "duplicates": 50,
        "refused": 0, "refused_reasons": {},
    }  # fmt: skip
    assert (await a.take(_upload(101, 200)))["stored"] == 50
    with engine.connect() as conn:
        row = conn.execute(select(ForwardStream.__table__)).one()
        raw = count_frames(conn)
    assert (row.acked_seq, row.frames, raw) == (200, 200, 200)


async def test_frames_sharing_a_timestamp_split_by_a_restart_are_each_archived(
    engine: Engine, db_url: str
) -> None:
    """Frames of one id sharing a timestamp (a multi-frame record, a log's resolution) are each
    archived under their own index within the group. Split between two uploads with the
    central restarted in between, the second frame continues the group's indices from the
    archive: starting at 0 again, it would be stored over the first and lost."""
    settings = Settings(database_url=db_url, vehicles=[VehicleConfig(id="VAN-1")])
    first, second = (T0, 0x18FFD61E, "d809b013ba7cc87d", 1), (T0, 0x18FFD61E, "d909b013ba7cc87d", 1)
    before = ForwardIngest(settings, engine)
    answer = await before.take(Upload("s1", "VAN-1", "VAN-1/can0", (30,), 1, [first]))
    assert answer["stored"] == 1
    after = ForwardIngest(settings, engine)  # another process: nothing of the first in memory
    answer = await after.take(Upload("s1", "VAN-1", "VAN-1/can0", (30,), 2, [second]))
    assert (answer["acked_seq"], answer["stored"]) == (2, 1)
    with engine.connect() as conn:
        assert count_frames(conn) == 2
