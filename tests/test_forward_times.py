"""Forwarded frames with absurd times (a vehicle computer with a dead clock: 0, the year 3000,
1e308) are refused one by one: not stored, counted per stream in the answer and in /metrics,
and acknowledged, so the forwarder forgets them and the batch's good frames are stored. Both
engines."""

from __future__ import annotations

import asyncio
import contextlib
import time
from pathlib import Path
from typing import Any

import httpx

from eqgw.forward.buffer import FrameBuffer
from eqgw.forward.uploader import Uploader, UploaderStatus, UploadSettings
from eqgw.security.keys import Scope, create_key
from tests.api_helpers import served, wait_for
from tests.db_helpers import archived_frames

VOLTS = "d809b013ba7cc87d"
CAN_ID = 0x18FFD61E  # equalizer voltages from SA 0x1E
YEAR_3000 = 32503680000.0
RAW_DAYS = 30.0


def _absurd(now: float) -> list[float]:
    """Dead clocks (0, ±1e308, the year 3000), a clock 10 minutes fast, one older than the raw
    retention."""
    return [0.0, 1e308, -1e308, YEAR_3000, now + 600, now - (RAW_DAYS + 1) * 86400]


def _frames(now: float) -> list[list[Any]]:
    """Six good frames (a second apart, the last ones up to the future window) with the
    absurd ones between them."""
    good = [now - 20 + i for i in range(4)] + [now + 60, now - (RAW_DAYS - 1) * 86400]
    out: list[list[Any]] = []
    for g, bad in zip(good, _absurd(now), strict=True):
        out += [[g, CAN_ID, VOLTS, 1], [bad, CAN_ID, VOLTS, 1]]
    return out


async def test_frames_with_absurd_times_are_refused_and_acknowledged(
    db_url: str, tmp_path: Path
) -> None:
    async with served(db_url, vehicles=2, config={"retention": {"raw_days": RAW_DAYS}}) as s:
        _, key = await asyncio.to_thread(
            create_key, s.rt.engine, "bus 1", "ingest", scope=Scope.of([], ["SIM-001"])
        )
        hdr = {"Authorization": f"Bearer {key}"}
        now = time.time()
        body = {"stream": "dead-clock", "vehicle": "SIM-001", "bus": "SIM-001/fwd",
                "first_seq": 1, "frames": _frames(now)}  # fmt: skip
        r = await s.client.post("/api/v1/ingest/frames", json=body, headers=hdr)
        assert r.status_code == 200, r.text
        ack = r.json()
        # Everything acknowledged (the forwarder forgets the refused ones too), six stored.
        wanted = {"acked_seq": 12, "stored": 6, "refused": 6,
                  "refused_reasons": {"future": 3, "too_old": 3}}  # fmt: skip
        assert {k: ack.get(k) for k in wanted} == wanted, ack
        rows = [f for f in archived_frames(db_url) if f.bus == "SIM-001/fwd"]
        stored = sorted(row.ts for row in rows)
        assert len(stored) == 6, stored
        assert now - RAW_DAYS * 86400 < stored[0] and stored[-1] <= now + 300, stored
        # Sent again: nothing stored twice, nothing refused twice.
        r = await s.client.post("/api/v1/ingest/frames", json=body, headers=hdr)
        assert r.json()["duplicates"] == 12 and r.json()["refused"] == 0, r.text

        # Per stream in /metrics (with an admin key: the series names a vehicle).
        text = (await s.client.get("/metrics", headers=s.auth())).text
        series = (
            'eqgw_forward_frames_refused_total{bus="SIM-001/fwd",reason="%s",'
            'stream="dead-clock",vehicle="SIM-001"}'
        )
        assert f"{series % 'future'} 3.0" in text, text
        assert f"{series % 'too_old'} 3.0" in text, text
        anonymous = (await s.client.get("/metrics")).text
        assert "dead-clock" not in anonymous

        # The forwarder: a buffer holding the same frames empties (the refused ones never
        # block it) and counts what was refused. Its status, read the moment the buffer has
        # forgotten the frames (in the uploader's thread, before its loop runs again), counts
        # every one of them: an empty buffer never shows beside none acknowledged.
        seen: list[UploaderStatus] = []

        class WatchedBuffer(FrameBuffer):
            def ack(self, seq: int) -> int:
                forgotten = super().ack(seq)
                seen.append(uploader.status())
                return forgotten

        buffer = WatchedBuffer(tmp_path / "fwd.db")
        buffer.add((f[0], f[1], bytes.fromhex(f[2]), f[3]) for f in _frames(time.time()))
        uploader = Uploader(
            buffer,
            UploadSettings(
                url="http://test/api/v1",
                key=key,
                vehicle="SIM-001",
                bus="SIM-001/fwd2",
                backoff_initial_s=0.05,
            ),
            transport=httpx.ASGITransport(app=s.app),
        )
        task = asyncio.create_task(uploader.run())
        try:

            async def emptied() -> bool:
                return buffer.rows == 0

            await wait_for(emptied, timeout=30, what="the buffer emptied")
            st = uploader.status()
            assert (st.frames_acked, st.frames_refused, st.failures) == (12, 6, 0), st
            assert [(x.frames_acked, x.frames_refused) for x in seen] == [(12, 6)], seen
            assert seen[0].last_ack_at is not None, seen
        finally:
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await task
            buffer.close()
