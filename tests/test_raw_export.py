"""Raw export: `GET /vehicles/{id}/raw` and `eqgw export` write the archive as candump, ASC,
BLF and MF4 with python-can's writers; python-can's readers and `eqgw replay` read every
format back bit for bit (time, identifier, extended flag, DLC, data, order, frames of one time
and identifier), across pages of the archive, on SQLite and PostgreSQL."""

from __future__ import annotations

import asyncio
import random
import struct
import time
from pathlib import Path
from typing import Any

import can
import pytest
from sqlalchemy import Engine, text

from eqgw.bus.export import FORMATS, LogExport, export_chunks
from eqgw.bus.replay import open_log_reader
from eqgw.cli import main
from eqgw.ingest.replay import replay_file
from eqgw.security.keys import Scope, create_key
from eqgw.store import archive, queries
from eqgw.store.archive import Frame, word_of
from eqgw.store.engine import create_engine
from tests.api_helpers import served
from tests.fixtures import mixed_log
from tests.test_ingest_replay import VMAP, _settings

V = "/api/v1"
START = mixed_log.START
# After the fixture's two minutes: a frame every 10 s for two hours (the export crosses many
# pages of the archive), and two frames of one time and identifier (seq 0 and 1).
SPARSE = [START + 600.0 + 10.0 * i + 0.000123 for i in range(720)]
END = SPARSE[-1] + 1.0
TWINS = START + 300.5
Key = tuple[int, bytes, int, int, bytes]  # (sa, ts bits, identifier word, seq, data)
# The fixture's frames are a year old or more: the gateway's retention must keep them.
KEEP = {"retention": {"raw_days": 36500, "rollup_days": 36500}}


def _bits(ts: float) -> bytes:
    return struct.pack("<d", ts)


def _log(tmp_path: Path) -> Path:
    lines = mixed_log.LOG.read_text().splitlines()
    lines += [f"({TWINS:.6f}) can0 18FFD41E#0102030405060708 R"]
    lines += [f"({TWINS:.6f}) can0 18FFD41E#0807060504030201 R"]
    lines += [
        f"({t:.6f}) can0 18FFD41E#{i % 256:02X}000114FFFFFFFF R" for i, t in enumerate(SPARSE)
    ]
    path = tmp_path / "long.log"
    path.write_text("\n".join(lines) + "\n")
    return path


def _archive_of(engine: Engine, vehicle: str) -> list[Key]:
    """The vehicle's archived frames as (sa, ts bits, word, seq, data), in time order."""
    with engine.connect() as conn:
        sas = {
            int(i): int(sa)
            for i, sa in conn.execute(
                text("SELECT id, sa FROM units WHERE vehicle_id = :v"), {"v": vehicle}
            )
        }
        frames = archive.read_frames(conn, sorted(sas))
    return [(sas[u], _bits(f.ts), f.word, f.seq, f.data) for u, f in frames]


def _read_back(path: Path) -> list[tuple[bytes, int, bool, int, bytes, int]]:
    """(ts bits, identifier, extended, DLC, data, channel) of every frame python-can reads."""
    with open_log_reader(path, absolute_asc=True) as reader:
        return [
            (
                _bits(m.timestamp),
                m.arbitration_id,
                m.is_extended_id,
                m.dlc,
                bytes(m.data),
                int(str(m.channel).removeprefix("can")),
            )
            for m in reader
        ]


def _expected(frames: list[Key]) -> list[tuple[bytes, int, bool, int, bytes, int]]:
    return [(ts, w & 0x1FFFFFFF, bool(w & 0x80000000), len(d), d, 0) for _, ts, w, _, d in frames]


@pytest.fixture
def stored(db_url: str, tmp_path: Path) -> list[Key]:
    """The fixture log (with the twins and the sparse frames) replayed into the database;
    BUS-101's archive as it holds it."""
    summary = replay_file(_log(tmp_path), VMAP, _settings(db_url))
    assert summary.writer.pending_rows == 0
    engine = create_engine(db_url)
    try:
        frames = _archive_of(engine, "BUS-101")
    finally:
        engine.dispose()
    twins = [f for f in frames if f[1] == _bits(TWINS)]
    assert [(f[3], f[4]) for f in twins] == [(0, bytes(range(1, 9))), (1, bytes(range(8, 0, -1)))]
    assert len(frames) > 720
    return frames


async def test_an_export_longer_than_the_request_deadline_is_whole(
    db_url: str, tmp_path: Path, stored: list[Key], monkeypatch: pytest.MonkeyPatch
) -> None:
    """Each page of the file has the request's database deadline of its own: an export
    whose pages together take longer than one deadline (a long range, a slow client) is
    whole, not cut part-way."""
    # A page sleeps under a quarter of the deadline: the rest (2.3 s) is its margin on a loaded
    # machine.
    deadline_s, nap_s = 3.0, 0.7
    real = archive.read_page
    pages = 0

    def slow(*args: Any) -> Any:
        nonlocal pages
        pages += 1
        time.sleep(nap_s)
        return real(*args)

    async with served(db_url, vehicles=1, config=KEEP, db_deadline_s=deadline_s) as s:
        monkeypatch.setattr(archive, "read_page", slow)
        r = await s.client.get(
            f"{V}/vehicles/BUS-101/raw",
            params={"from": str(START - 1), "to": str(END), "format": "candump"},
            headers=s.auth(),
        )
        assert r.status_code == 200, r.text
        assert pages * nap_s > 2 * deadline_s, pages  # two deadlines and more in all
        path = tmp_path / "all.log"
        path.write_bytes(r.content)
        assert _read_back(path) == _expected(stored)


async def test_every_format_reads_back_bit_for_bit(
    db_url: str, tmp_path: Path, stored: list[Key]
) -> None:
    want = _expected(stored)
    async with served(db_url, vehicles=1, config=KEEP) as s:
        for fmt, suffix in FORMATS.items():
            r = await s.client.get(
                f"{V}/vehicles/BUS-101/raw",
                params={"from": str(START - 1), "to": str(END), "format": fmt},
                headers=s.auth(),
            )
            assert r.status_code == 200, r.text
            binary = fmt in ("blf", "mf4")
            assert r.headers["content-type"].startswith(
                "application/octet-stream" if binary else "text/plain"
            )
            assert r.headers["content-disposition"].endswith(f'{suffix}"')
            assert r.headers["x-eqgw-channels"] == "0=BUS-101/can0"
            path = tmp_path / f"api{suffix}"
            path.write_bytes(r.content)
            assert _read_back(path) == want, fmt
        # A range without frames is an empty log, still readable.
        r = await s.client.get(
            f"{V}/vehicles/BUS-101/raw", params={"format": "blf"}, headers=s.auth()
        )
        assert r.status_code == 200
        (tmp_path / "empty.blf").write_bytes(r.content)
        assert _read_back(tmp_path / "empty.blf") == []


async def test_refusals_and_scope(db_url: str, stored: list[Key]) -> None:
    async with served(db_url, vehicles=1, config=KEEP) as s:
        url = f"{V}/vehicles/BUS-101/raw"
        r = await s.client.get(url, params={"format": "pcap"}, headers=s.auth())
        assert r.status_code == 422
        r = await s.client.get(url, params={"from": "yesterday"}, headers=s.auth())
        assert r.status_code == 422 and r.json()["type"] == "invalid_time"
        r = await s.client.get(url, params={"from": "2", "to": "1"}, headers=s.auth())
        assert r.status_code == 422
        assert (await s.client.get(url)).status_code == 401
        _, other = await asyncio.to_thread(
            create_key, s.rt.engine, "bus 102", "viewer", scope=Scope.of([], ["BUS-102"])
        )
        hidden = await s.client.get(url, headers=s.auth(other))
        nope = await s.client.get(f"{V}/vehicles/NOPE-1/raw", headers=s.auth(other))
        assert hidden.status_code == nope.status_code == 404
        assert hidden.json()["type"] == nope.json()["type"] == "unknown_vehicle"
        seen = await s.client.get(
            f"{V}/vehicles/BUS-102/raw",
            params={"from": str(START - 1), "to": str(END)},
            headers=s.auth(other),
        )
        assert seen.status_code == 200 and seen.text.count("\n") > 10
        spec = s.app.openapi()["paths"][f"{V}/vehicles/{{vehicle_id}}/raw"]["get"]
        assert set(spec["responses"]["200"]["content"]) == {
            "application/octet-stream",
            "text/plain",
        }
        assert spec["operationId"] == "export_vehicle_raw"
        fmt = next(p for p in spec["parameters"] if p["name"] == "format")
        assert fmt["schema"]["enum"] == ["candump", "asc", "blf", "mf4"]


async def test_live_frames_not_packed_yet_are_exported(db_url: str, tmp_path: Path) -> None:
    """A simulated vehicle's frames of the last seconds wait in raw_recent: the export has
    them, as the archive does."""
    async with served(db_url, vehicles=1, config=KEEP) as s:

        def count(conn: Any) -> int:
            return int(conn.execute(text("SELECT count(*) FROM raw_recent")).scalar_one())

        for _ in range(400):
            if await s.rt.db(count) > 20:
                break
            await asyncio.sleep(0.05)
        # The simulated clock runs ahead of the wall clock (4x): `to` well past now. BLF:
        # the simulator's times are not on the microsecond grid.
        ahead = {"from": "0", "to": str(time.time() + 86400), "format": "blf"}
        r = await s.client.get(f"{V}/vehicles/SIM-001/raw", params=ahead, headers=s.auth())
        assert r.status_code == 200
        path = tmp_path / "live.blf"
        path.write_bytes(r.content)
        got = _read_back(path)
        assert len(got) > 20

        def frames(conn: Any) -> list[archive.UnitFrame]:
            units = [u["id"] for u in queries.list_units(conn) if u["vehicle_id"] == "SIM-001"]
            return archive.read_frames(conn, units)

        archived = await s.rt.db(frames)
        keys = {(_bits(f.ts), f.can_id, f.data) for _, f in archived}
        assert all((ts, cid, data) in keys for ts, cid, _, _, data, _ in got)


def test_eqgw_export_and_replay_of_every_format(
    db_url: str, tmp_path: Path, stored: list[Key], capsys: pytest.CaptureFixture[str]
) -> None:
    """`eqgw export` writes each format; python-can reads it back exactly and `eqgw replay`
    of it into another database holds the same archive, bit for bit."""
    want = _expected(stored)
    for fmt, suffix in FORMATS.items():
        out = tmp_path / f"cli{suffix}"
        args = ["export", "BUS-101", "--from", str(START - 1), "--to", str(END)]
        assert main([*args, "--out", str(out), "--db", db_url]) == 0
        assert f"{len(stored)} frames of BUS-101 written" in capsys.readouterr().out
        assert _read_back(out) == want, fmt
        again = f"sqlite:///{tmp_path / f'replayed-{fmt}.db'}"
        replay = ["replay", str(out), "--vehicle", "AGAIN", "--sa", "30,31", "--db", again, "-q"]
        assert main(replay) == 0, capsys.readouterr()
        engine = create_engine(again)
        try:
            assert _archive_of(engine, "AGAIN") == stored, fmt
        finally:
            engine.dispose()
    capsys.readouterr()
    assert main(["export", "NOPE", "--out", str(tmp_path / "x.log"), "--db", db_url]) == 1
    assert "no vehicle 'NOPE'" in capsys.readouterr().err
    assert main(["export", "BUS-101", "--out", str(tmp_path / "x.txt"), "--db", db_url]) == 2
    empty = f"sqlite:///{tmp_path / 'never-migrated.db'}"
    assert main(["export", "BUS-101", "--out", str(tmp_path / "y.log"), "--db", empty]) == 1
    assert "the database cannot be read" in capsys.readouterr().err


def test_time_resolution_of_each_format(tmp_path: Path) -> None:
    """BLF and MF4 keep any epoch time to the bit; candump and ASC carry microseconds (a time
    on the microsecond grid, as SocketCAN and candump logs stamp, comes back to the bit)."""
    rng = random.Random(5)
    t = START
    page = []
    for i in range(500):
        t += rng.random() * 0.05
        ts = t if i % 2 else round(t, 6)
        data = bytes(rng.getrandbits(8) for _ in range(rng.choice((0, 1, 8))))
        page.append((i % 3, Frame(ts, word_of(0x18FF0000 + i % 7), 0, data)))
    for fmt, suffix in FORMATS.items():
        path = tmp_path / f"t{suffix}"
        with path.open("wb") as fh:
            for chunk in export_chunks([page[:200], page[200:]], LogExport(fmt)):
                fh.write(chunk)
        got = _read_back(path)
        exact = fmt in ("blf", "mf4")
        assert got == [
            (
                _bits(f.ts if exact else round(f.ts, 6)),
                f.can_id,
                True,
                len(f.data),
                f.data,
                ch,
            )
            for ch, f in page
        ], fmt


def test_text_exports_are_made_page_by_page() -> None:
    """candump and ASC give each page's text as it is written (the HTTP answer streams it);
    BLF and MF4 are read out once finished, from a temporary file removed at the end."""
    page = [(0, Frame(START + i, word_of(0x18FFD41E), 0, b"\x01\x02")) for i in range(3)]
    for fmt in ("candump", "asc"):
        export = LogExport(fmt)
        first = export.write(page)
        assert first.count(b"18FFD41E") == 3
        assert export.write(page[:1]).count(b"18FFD41E") == 1
        export.finish()
        export.close()
    export = LogExport("blf")
    assert export.write(page) == b""
    assert export.finish() == b""
    body = export.read()
    assert body.startswith(b"LOGG")
    folder = export._dir
    assert folder is not None and folder.exists()
    export.close()
    assert not folder.exists()
    with can.BLFReader(__import__("io").BytesIO(body)) as reader:
        assert len(list(reader)) == 3
