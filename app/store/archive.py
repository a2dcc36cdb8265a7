"""The raw archive: every equalizer frame as received, packed per unit and minute, compressed,
and read back bit for bit.

Layout. A unit's frames of one minute (`BLOCK_S`) are one row of `raw_blocks`: the frames in
key order (timestamp, identifier, seq), packed column by column (`pack_block`) and compressed
with zlib. The frames of minutes not packed yet wait in `raw_recent`, one row each, keyed as
the archive always was (unit, timestamp, identifier, seq). The writer packs a minute
(`compact`) once it ended `COMPACT_AFTER_S` ago; readers (`read_page`) merge both tables, so
a frame is found wherever it is.

Why this shape. One row per frame costs about 132 bytes on PostgreSQL (tuple header, item
pointer, index entry) for 13-21 bytes of frame. Packed by minute, a frame costs about 3 bytes
with the row and index overhead shared by the minute's 120 frames (bench/archive_size.py).
The columns (timestamp deltas, identifiers, sequence numbers, lengths, each identifier's
payloads together) put alike bytes side by side, which zlib folds: about 4 B/frame packed row
by row, 2-3.7 packed by column on the test fixtures. zlib is in every Python and every
language's standard library, takes ~10 us for a minute block, and at this block size
compresses as well as lzma (~40 times slower, with a larger container) and better than bz2.

Idempotency. A frame's key is (unit, timestamp, identifier word, seq), seq being its place
among the unit's frames with that identifier and timestamp (as the ingest numbers them): a
block holds each key once, a merge (`merge_frames`) adds only keys it lacks, and raw_recent
refuses a key it holds. A replay, a retried batch or a journal written twice adds nothing;
two frames with the same time and identifier (seq 0 and 1) are both kept.

Timestamps are stored as the 8 bytes of the float the ingest gave them (the bit pattern's
difference to the previous frame's), so a frame reads back to the same float, to the bit.
"""

from __future__ import annotations

import struct
import time
import zlib
from collections.abc import Iterable, Mapping, Sequence
from itertools import accumulate, pairwise
from typing import NamedTuple

from sqlalchemy import Connection, Engine, bindparam, func, select, text

from eqgw.store.blockrows import BlockKey, BlockRow, lock_blocks, pg_array, save_blocks, start_of
from eqgw.store.errors import StoreError
from eqgw.store.models import RawBlock, RawRecent, Unit, table_of

# A block holds one unit's frames of one minute, starting at a multiple of BLOCK_S.
BLOCK_S = 60.0
# A minute is packed once it ended this long ago (frames that come later merge into it).
COMPACT_AFTER_S = 60.0
# How often the writer packs the minutes that are due.
COMPACT_EVERY_S = 30.0
# Frames packed per compaction transaction.
COMPACT_FRAMES = 20_000
# Seconds of history read per page (`read_page`): a page of one vehicle is a few MB at most.
PAGE_S = 900.0

# The identifier word, as SocketCAN's can_id: the identifier and three flags.
CAN_EFF_FLAG = 0x80000000  # 29-bit (extended) identifier
CAN_RTR_FLAG = 0x40000000  # remote frame
CAN_ERR_FLAG = 0x20000000  # error frame
CAN_EFF_MASK = 0x1FFFFFFF

_LAYOUT = 1
_HEADER = struct.Struct("<BI")  # layout version, frame count
_MASK64 = (1 << 64) - 1
_ZLIB_LEVEL = 9

_blocks = table_of(RawBlock)
_recent = table_of(RawRecent)
_units = table_of(Unit)

UnitKey = tuple[str, int]  # (bus, source address), as eqgw.store.writes
# A writer's raw frame: its unit and values (eqgw.store.writes.RawFrameValues; `extended`,
# `remote` and `error` may say what the bare identifier does not).
Row = tuple[UnitKey, Mapping[str, object]]


class ArchiveError(StoreError):
    """A block that cannot be unpacked (damaged, or of a layout this version does not know)."""


class Frame(NamedTuple):
    """One archived frame. Tuples order as the archive does: time, identifier, seq."""

    ts: float
    word: int  # identifier | CAN_EFF_FLAG | CAN_RTR_FLAG | CAN_ERR_FLAG
    seq: int
    data: bytes

    @property
    def can_id(self) -> int:
        return self.word & (CAN_EFF_MASK if self.word & CAN_EFF_FLAG else 0x7FF)

    @property
    def is_extended(self) -> bool:
        return bool(self.word & CAN_EFF_FLAG)

    @property
    def is_remote(self) -> bool:
        return bool(self.word & CAN_RTR_FLAG)

    @property
    def is_error(self) -> bool:
        return bool(self.word & CAN_ERR_FLAG)


def word_of(
    can_id: int, *, extended: bool = True, remote: bool = False, error: bool = False
) -> int:
    """The identifier word of a frame (SocketCAN's can_id layout)."""
    word = can_id & (CAN_EFF_MASK if extended else 0x7FF)
    if extended:
        word |= CAN_EFF_FLAG
    if remote:
        word |= CAN_RTR_FLAG
    if error:
        word |= CAN_ERR_FLAG
    return word


def block_start(ts: float) -> float:
    """The start of the block holding `ts`: start <= ts < start + BLOCK_S."""
    return start_of(ts, BLOCK_S)


# -- the block format ---------------------------------------------------------------------


def pack_block(frames: Iterable[Frame]) -> bytes:
    """Frames as one compressed block (sorted into key order; keys are expected unique).

    Layout 1, before compression, little-endian: the layout number (u8) and the frame count
    n (u32); n u64, the timestamps' float64 bit patterns, the first as is and each other as
    its difference to the previous (mod 2**64); n u32 identifier words; n u16 seq; n u8 data
    lengths; then the payloads, each identifier's together (identifiers in the order they
    first appear, each one's payloads in frame order)."""
    rows = sorted(frames)
    n = len(rows)
    bits = struct.unpack(f"<{n}Q", struct.pack(f"<{n}d", *[f.ts for f in rows]))
    deltas = [(b - a) & _MASK64 for a, b in pairwise((0, *bits))]
    streams: dict[int, list[bytes]] = {}
    for f in rows:
        streams.setdefault(f.word, []).append(f.data)
    payload = b"".join(
        [
            _HEADER.pack(_LAYOUT, n),
            struct.pack(f"<{n}Q", *deltas),
            struct.pack(f"<{n}I", *[f.word for f in rows]),
            struct.pack(f"<{n}H", *[f.seq for f in rows]),
            bytes([len(f.data) for f in rows]),
            *(b"".join(parts) for parts in streams.values()),
        ]
    )
    return zlib.compress(payload, _ZLIB_LEVEL)


def unpack_block(blob: bytes) -> list[Frame]:
    """The frames of a block, in key order, bit for bit as packed."""
    try:
        payload = zlib.decompress(blob)
        layout, n = _HEADER.unpack_from(payload)
    except (zlib.error, struct.error) as exc:
        raise ArchiveError(f"a raw block cannot be read: {exc}") from exc
    if layout != _LAYOUT:
        raise ArchiveError(f"a raw block has layout {layout}; this version reads {_LAYOUT}")
    pos = _HEADER.size
    try:
        deltas = struct.unpack_from(f"<{n}Q", payload, pos)
        pos += 8 * n
        words = struct.unpack_from(f"<{n}I", payload, pos)
        pos += 4 * n
        seqs = struct.unpack_from(f"<{n}H", payload, pos)
        pos += 2 * n
        lengths = payload[pos : pos + n]
        pos += n
    except struct.error as exc:
        raise ArchiveError(f"a raw block is cut short: {exc}") from exc
    if len(lengths) != n:
        raise ArchiveError("a raw block is cut short")
    bits = list(accumulate(deltas, lambda a, b: (a + b) & _MASK64))
    stamps = struct.unpack(f"<{n}d", struct.pack(f"<{n}Q", *bits))
    # Where each identifier's payloads start: identifiers in order of first appearance.
    totals: dict[int, int] = {}
    for w, size in zip(words, lengths, strict=True):
        totals[w] = totals.get(w, 0) + size
    offsets: dict[int, int] = {}
    for w, size in totals.items():
        offsets[w] = pos
        pos += size
    if pos != len(payload):
        raise ArchiveError("a raw block's payloads do not match its lengths")
    out: list[Frame] = []
    for ts, w, seq, size in zip(stamps, words, seqs, lengths, strict=True):
        at = offsets[w]
        out.append(Frame(ts, w, seq, payload[at : at + size]))
        offsets[w] = at + size
    return out


def merge_frames(stored: Sequence[Frame], new: Iterable[Frame]) -> tuple[list[Frame], int]:
    """`stored` with the frames of `new` whose key it lacks (the first of a repeated key
    wins); returns the merged frames in key order and how many were added."""
    have = {f[:3] for f in stored}
    added: list[Frame] = []
    for f in new:
        k = f[:3]
        if k not in have:
            have.add(k)
            added.append(f)
    if not added:
        return list(stored), 0
    return sorted([*stored, *added]), len(added)


# -- writing --------------------------------------------------------------------------------


def _frame_of(values: Mapping[str, object]) -> Frame:
    """A writer row's frame. The ingest archives extended data frames (eqgw.ingest.pipeline)
    and gives the bare identifier; a row may say otherwise (`extended`, `remote`, `error`)."""
    ts, can_id, seq, data = values["ts"], values["can_id"], values["seq"], values["data"]
    if not (
        isinstance(ts, int | float)
        and isinstance(can_id, int)
        and isinstance(seq, int)
        and isinstance(data, bytes | bytearray | memoryview)
    ):
        raise TypeError(f"not a raw frame: {values!r}")
    word = word_of(
        can_id,
        extended=bool(values.get("extended", True)),
        remote=bool(values.get("remote", False)),
        error=bool(values.get("error", False)),
    )
    return Frame(ts, word, seq, bytes(data))


def store_frames(
    conn: Connection, rows: Sequence[Row], ids: dict[UnitKey, int]
) -> tuple[list[Row], int]:
    """The writer's raw frames: those whose minute is packed already are merged into its
    block here; the others are returned as `raw_recent` rows (for the batch's insert), with
    the count of frames the blocks gained. Inside the caller's transaction."""
    if not rows:
        return [], 0
    frames = [(ids[key], key, _frame_of(values)) for key, values in rows]
    spans: dict[int, list[float]] = {}
    for uid, _, f in frames:
        span = spans.get(uid)
        if span is None:
            spans[uid] = [f.ts, f.ts]
        elif f.ts < span[0]:
            span[0] = f.ts
        elif f.ts > span[1]:
            span[1] = f.ts
    packed = _packed_blocks(conn, spans)
    if not packed:  # the usual case: live frames, newer than any block
        return [
            (key, {"ts": f.ts, "can_id": f.word, "seq": f.seq, "data": f.data})
            for _, key, f in frames
        ], 0
    recent: list[Row] = []
    late: dict[BlockKey, list[Frame]] = {}
    for uid, key, f in frames:
        start = block_start(f.ts)
        if (uid, start) in packed:
            late.setdefault((uid, start), []).append(f)
        else:
            recent.append((key, {"ts": f.ts, "can_id": f.word, "seq": f.seq, "data": f.data}))
    added = merge_into_blocks(conn, late) if late else 0
    return recent, added


def _packed_blocks(conn: Connection, spans: dict[int, list[float]]) -> set[BlockKey]:
    """The blocks stored within each unit's span (usually none: live frames are newer)."""
    found: set[BlockKey] = set()
    if conn.dialect.name == "postgresql":
        uids = list(spans)
        result = conn.execute(
            text(
                "SELECT b.unit_id, b.ts FROM unnest(CAST(:u AS int[]), CAST(:lo AS float8[]), "
                "CAST(:hi AS float8[])) AS s(u, lo, hi) "
                "JOIN raw_blocks b ON b.unit_id = s.u AND b.ts BETWEEN s.lo AND s.hi"
            ),
            {
                "u": pg_array(uids),
                "lo": pg_array(block_start(spans[u][0]) for u in uids),
                "hi": pg_array(spans[u][1] for u in uids),
            },
        )
        found.update((int(u), float(t)) for u, t in result)
        return found
    b = _blocks.c
    stmt = select(b.unit_id, b.ts).where(
        b.unit_id == bindparam("u"), b.ts.between(bindparam("lo"), bindparam("hi"))
    )
    for uid, (lo, hi) in spans.items():
        for u, t in conn.execute(stmt, {"u": uid, "lo": block_start(lo), "hi": hi}):
            found.add((int(u), float(t)))
    return found


def merge_into_blocks(conn: Connection, groups: dict[BlockKey, list[Frame]]) -> int:
    """Merge frames into their blocks (made when missing); returns the frames added. The
    blocks are locked while merged (PostgreSQL: FOR UPDATE, in key order; SQLite: the
    transaction's write lock)."""
    if not groups:
        return 0
    keys = sorted(groups)
    stored = lock_blocks(conn, _blocks, keys)
    inserts: list[BlockRow] = []
    updates: list[BlockRow] = []
    added = 0
    for key in keys:
        blob = stored.get(key)
        merged, n = merge_frames(unpack_block(blob) if blob is not None else [], groups[key])
        if not n:
            continue
        added += n
        row: BlockRow = {"u": key[0], "t": key[1], "n": len(merged), "d": pack_block(merged)}
        (updates if blob is not None else inserts).append(row)
    save_blocks(conn, _blocks, "frames", updates, inserts)
    return added


# -- packing the minutes that are due -------------------------------------------------------


def compact(
    engine: Engine,
    *,
    before: float | None = None,
    max_frames: int = COMPACT_FRAMES,
    budget_s: float | None = None,
) -> int:
    """Pack the frames of `raw_recent` whose minute ended by `before` (default
    `COMPACT_AFTER_S` ago) into their blocks, `max_frames` a transaction; returns the frames
    packed. With `budget_s`, no transaction starts after that many seconds (the rest waits
    for the next call)."""
    before = time.time() - COMPACT_AFTER_S if before is None else before
    edge = block_start(before)
    if engine.dialect.name == "sqlite":
        engine = engine.execution_options(sqlite_begin="IMMEDIATE")
    began = time.monotonic()
    total = 0
    while True:
        with engine.begin() as conn:
            n, more = compact_once(conn, edge, max_frames)
        total += n
        if not more or (budget_s is not None and time.monotonic() - began >= budget_s):
            return total


def compact_once(conn: Connection, edge: float, max_frames: int) -> tuple[int, bool]:
    """One transaction of `compact`: up to `max_frames` frames older than `edge` (a block
    start) moved from raw_recent into their blocks. Returns (frames moved, whether more are
    due). On PostgreSQL one gateway packs at a time (a transaction advisory lock; the others
    skip their turn), and exactly the rows read are deleted, so a frame another process
    adds meanwhile stays for the next turn."""
    if conn.dialect.name == "postgresql":
        mine = conn.execute(
            text(
                "SELECT pg_try_advisory_xact_lock(hashtextextended('eqgw-raw-compaction/' || "
                "current_database() || '/' || current_schema(), 0))"
            )
        ).scalar_one()
        if not mine:
            return 0, False
    r = _recent.c
    rows = conn.execute(
        select(r.unit_id, r.ts, r.can_id, r.seq, r.data)
        .where(r.ts < edge)
        .order_by(r.unit_id, r.ts)
        .limit(max_frames + 1)
    ).all()
    if not rows:
        return 0, False
    more = len(rows) > max_frames
    if more:
        rows = rows[:max_frames]
        # The last minute read may go on past the limit: it is packed whole next time.
        last = (rows[-1][0], block_start(rows[-1][1]))
        whole = [row for row in rows if (row[0], block_start(row[1])) != last]
        rows = whole or rows
    groups: dict[BlockKey, list[Frame]] = {}
    for uid, ts, word, seq, data in rows:
        groups.setdefault((uid, block_start(ts)), []).append(Frame(ts, word, seq, bytes(data)))
    merge_into_blocks(conn, groups)
    _delete_recent(conn, [(row[0], row[1], row[2], row[3]) for row in rows])
    return len(rows), more


def _delete_recent(conn: Connection, keys: list[tuple[int, float, int, int]]) -> None:
    if conn.dialect.name == "postgresql":
        columns = list(zip(*keys, strict=True))
        conn.execute(
            text(
                "DELETE FROM raw_recent r USING unnest(CAST(:u AS int[]), CAST(:t AS float8[]), "
                "CAST(:c AS int8[]), CAST(:s AS int2[])) AS k(u, t, c, s) "
                "WHERE r.unit_id = k.u AND r.ts = k.t AND r.can_id = k.c AND r.seq = k.s"
            ),
            {name: pg_array(col) for name, col in zip("utcs", columns, strict=True)},
        )
        return
    raw = conn.connection.driver_connection
    assert raw is not None
    raw.executemany(
        "DELETE FROM raw_recent WHERE unit_id = ? AND ts = ? AND can_id = ? AND seq = ?", keys
    )


# -- reading --------------------------------------------------------------------------------

UnitFrame = tuple[int, Frame]  # (unit id, frame)


def read_page(
    conn: Connection, unit_ids: Sequence[int], start: float, end: float
) -> tuple[list[UnitFrame], float | None]:
    """The frames of `unit_ids` with start <= ts < end, from the first one on and for
    `PAGE_S` of history at most, in (time, unit, identifier, seq) order; and where the next
    page starts (None: nothing is left before `end`). A page is read from the blocks and from
    raw_recent alike; a frame in both (a race of two gateways) is given once."""
    if not unit_ids or not start < end:
        return [], None
    units = list(unit_ids)
    b, r = _blocks.c, _recent.c
    # The first frame's minute, unit by unit: each an index probe (a min() over several units
    # would walk every entry up to `end`, for every page).
    firsts: list[float] = []
    for uid in units:
        for table, ts, lo in ((_blocks, b.ts, block_start(start)), (_recent, r.ts, start)):
            t = conn.execute(
                select(ts).where(table.c.unit_id == uid, ts >= lo, ts < end).order_by(ts).limit(1)
            ).scalar_one_or_none()
            if t is not None:
                firsts.append(max(float(t), start))  # a block may begin before `start`
    if not firsts:
        return [], None
    first = min(firsts)
    page_end = min(end, block_start(first) + PAGE_S)
    out: list[UnitFrame] = []
    for uid, blob in conn.execute(
        select(b.unit_id, b.data).where(
            b.unit_id.in_(units), b.ts >= block_start(first), b.ts < page_end
        )
    ):
        out += [(uid, f) for f in unpack_block(bytes(blob)) if start <= f.ts < page_end]
    for uid, ts, word, seq, data in conn.execute(
        select(r.unit_id, r.ts, r.can_id, r.seq, r.data).where(
            r.unit_id.in_(units), r.ts >= first, r.ts < page_end
        )
    ):
        out.append((uid, Frame(ts, word, seq, bytes(data))))
    out.sort(key=_order)
    unique = [uf for i, uf in enumerate(out) if i == 0 or _key(out[i - 1]) != _key(uf)]
    return unique, (page_end if page_end < end else None)


def _order(uf: UnitFrame) -> tuple[float, int, int, int]:
    return uf[1].ts, uf[0], uf[1].word, uf[1].seq


_key = _order


def read_frames(
    conn: Connection, unit_ids: Sequence[int], start: float = 0.0, end: float = 1e12
) -> list[UnitFrame]:
    """Every frame of `unit_ids` with start <= ts < end (read page by page; for ranges
    known to be small, and tests)."""
    out: list[UnitFrame] = []
    cursor: float | None = start
    while cursor is not None:
        page, cursor = read_page(conn, unit_ids, cursor, end)
        out += page
    return out


def count_frames(conn: Connection, unit_ids: Sequence[int] | None = None) -> int:
    """Frames in the archive (of `unit_ids`, or all)."""
    b, r = _blocks.c, _recent.c
    packed = select(func.coalesce(func.sum(b.frames), 0))
    recent = select(func.count()).select_from(_recent)
    if unit_ids is not None:
        packed = packed.where(b.unit_id.in_(list(unit_ids)))
        recent = recent.where(r.unit_id.in_(list(unit_ids)))
    return int(conn.execute(packed).scalar_one()) + int(conn.execute(recent).scalar_one())


def last_groups(conn: Connection, bus: str) -> dict[tuple[str, int], tuple[float, dict[int, int]]]:
    """Per unit of `bus` (bus, sa): the timestamp of its newest archived frame not packed yet,
    and per identifier (without SocketCAN's flag) the highest `seq` stored at that timestamp.
    A pipeline that takes the bus over (another process, a rebuilt stream) continues those
    groups' indices from here (`IngestPipeline.continue_groups`): a frame sharing that
    timestamp and identifier is the next in its group, not a second index 0 that would be
    stored over the first."""
    u, r = _units.c, _recent.c
    newest = (
        select(r.unit_id, u.sa, func.max(r.ts).label("ts"))
        .join(_units, u.id == r.unit_id)
        .where(u.bus == bus)
        .group_by(r.unit_id, u.sa)
        .subquery()
    )
    n = newest.c
    rows = conn.execute(
        select(n.sa, n.ts, r.can_id, func.max(r.seq))
        .join(_recent, (r.unit_id == n.unit_id) & (r.ts == n.ts))
        .group_by(n.sa, n.ts, r.can_id)
    )
    out: dict[tuple[str, int], tuple[float, dict[int, int]]] = {}
    for sa, ts, word, seq in rows:
        # The archive holds extended data frames only: the identifier is the word's low bits,
        # as the pipeline keys it (`word_of` the other way).
        out.setdefault((bus, int(sa)), (float(ts), {}))[1][int(word) & CAN_EFF_MASK] = int(seq)
    return out
