"""Packed time series: measurements and battery states older than a horizon, packed per unit
and hour into compressed blocks, and read back value for value, bit for bit.

Layout. The writer stores every voltages frame as a `measurements` row and every battery
states frame as a `battery_states` row, as always. Once an hour of a unit (`BLOCK_S`) ended
`PACK_AFTER_S` before both the clock and the unit's newest data (`units.last_seen`), its rows
are packed (`compact`) into one row of `measurement_blocks` / `battery_blocks`: the rows in key
order, column by column, compressed with zlib. Readers (`read_rows`, and through it
eqgw.store.queries.series) read both the rows and the blocks, so a row is found wherever it is.
Rollups are made from the rows as they are written and are not touched by packing.

Why this shape. A row of four doubles costs about 90 bytes on PostgreSQL (tuple header, item
pointer, primary key entry) and a battery state about 130, for values that are 16-bit
fixed-point fields on the bus. Packed by hour, the row and index overhead is shared by the
hour's 1,200 measurements (720 battery states), and each column compresses on its own: a float
column whose values are all `k / 10**d` for integers k (the J1939 scaling: 0.005 V is
d = 3, 0.05 A d = 2, 0.1 % d = 1) is stored as the differences of the k, which are small
and alike; timestamps likewise when they are whole milliseconds or microseconds (log files,
the simulator). A column where some value is not such a decimal (NaN, an infinity, -0.0, a
float from a clock) is stored as the 8 bytes of each float instead, so every value reads back
to the same bits. Ints (index, states, raw temperature) are differences too; the battery name
is a small dictionary.

Idempotency. A block holds each key of its rows once ((ts) for measurements, (ts, idx) for
battery states, as the tables' primary keys); a row written late for an hour already packed is
merged into its block (`store_late_rows`) when its key is missing there, and dropped when it
is not, as the table's ON CONFLICT DO NOTHING would: replays add nothing, and the rollups
count a row only once. On PostgreSQL a writer whose batch reaches back past the horizon takes
a shared advisory lock that packing takes exclusively, so a row is never both packed and
inserted again behind the packer's back.
"""

from __future__ import annotations

import math
import struct
import time
import zlib
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from itertools import pairwise
from operator import itemgetter
from typing import TYPE_CHECKING, TypedDict, TypeVar, cast

from sqlalchemy import (
    Connection,
    Double,
    Engine,
    Integer,
    String,
    bindparam,
    func,
    select,
    text,
)

from eqgw.store.blockrows import BlockKey, BlockRow, lock_blocks, pg_array, save_blocks, start_of
from eqgw.store.errors import StoreError
from eqgw.store.models import (
    BatteryBlock,
    BatteryState,
    CoreTable,
    Measurement,
    MeasurementBlock,
    Unit,
    table_of,
)

if TYPE_CHECKING:
    from sqlalchemy import Select

# A block holds one unit's rows of one hour, starting at a multiple of BLOCK_S.
BLOCK_S = 3600.0
# An hour is packed once it ended this long before the clock and the unit's newest data.
PACK_AFTER_S = 3600.0
# Rows packed per transaction.
COMPACT_ROWS = 10_000

_LAYOUT = 1
_HEADER = struct.Struct("<BIB")  # layout, rows, columns
_ZLIB_LEVEL = 9
_MAX_DECIMALS = 6
# Column kinds in a block.
_NULL, _DECIMAL, _FLOAT, _INT, _TEXT = range(5)
_PLAIN = 0x80  # the "width" of int64 values stored as they are

UnitKey = tuple[str, int]  # (bus, source address), as eqgw.store.writes


class Timed(TypedDict):
    """What packing reads of the writer's values of a row by name: its time (the other
    columns are read by name as `object`, and stored as they are)."""

    ts: float


Row = tuple[UnitKey, Timed]
# The writer's rows of one series (eqgw.store.writes: a TypedDict of values per row).
R = TypeVar("R", bound=Row)
# A value of a packed table: a float column's, an int column's (an int is a float to the type
# checker), a text column's, or NULL.
Cell = float | str | None
# A row's values in table column order, unit_id left out (`ts` is the first column).
Values = tuple[float, *tuple[Cell, ...]]
# The same with the unit's id first: (unit_id, ts, ...).
UnitValues = tuple[int, *tuple[Cell, ...]]
# A row's primary key after unit_id: its one column's value (ts), or a tuple (ts, idx).
Key = Cell | tuple[Cell, ...]


class PackedError(StoreError):
    """A block that cannot be unpacked (damaged, or of a layout this version does not know)."""


@dataclass(frozen=True, slots=True)
class Series:
    """A table of rows and the table of its packed blocks."""

    rows: CoreTable
    blocks: CoreTable
    columns: tuple[str, ...]  # the row table's columns after unit_id, in order
    kinds: tuple[str, ...]  # "f" float, "i" int, "s" text, per column
    key: tuple[int, ...]  # positions in `columns` of the primary key after unit_id

    @property
    def name(self) -> str:
        return self.rows.name

    def key_of(self, values: Values) -> Key:
        if len(self.key) == 1:
            return values[self.key[0]]
        return tuple(values[i] for i in self.key)


def series_of(rows: CoreTable, blocks: CoreTable) -> Series:
    """The `Series` of a row table and its block table (their columns as defined)."""
    cols = [c for c in rows.columns if c.name != "unit_id"]
    kinds = []
    for c in cols:
        if isinstance(c.type, Double):
            kinds.append("f")
        elif isinstance(c.type, Integer):
            kinds.append("i")
        elif isinstance(c.type, String):
            kinds.append("s")
        else:  # pragma: no cover - the packed tables hold numbers and short names only
            raise TypeError(f"{rows.name}.{c.name}: no packing for {c.type}")
    names = tuple(c.name for c in cols)
    if names[0] != "ts":  # pragma: no cover - Values have the time first
        raise TypeError(f"{rows.name}: ts is not its first column after unit_id")
    pk = tuple(names.index(c.name) for c in rows.primary_key.columns if c.name != "unit_id")
    return Series(rows, blocks, names, tuple(kinds), pk)


MEASUREMENTS = series_of(table_of(Measurement), table_of(MeasurementBlock))
BATTERY_STATES = series_of(table_of(BatteryState), table_of(BatteryBlock))
SERIES = (MEASUREMENTS, BATTERY_STATES)
# Per table pruned by time, how far past its `ts` (a block's start) its last value may be:
# the retention deletes a block once all of it is past the cutoff.
BLOCK_SPAN_S = {MEASUREMENTS.blocks.name: BLOCK_S, BATTERY_STATES.blocks.name: BLOCK_S}

_units = table_of(Unit)


def block_start(ts: float) -> float:
    """The start of the block holding `ts`: start <= ts < start + BLOCK_S."""
    return start_of(ts, BLOCK_S)


# -- the block format ---------------------------------------------------------------------


def _is_positive_zero_or_nonzero(v: float) -> bool:
    return v != 0.0 or math.copysign(1.0, v) > 0


def _decimal_ints(values: Sequence[float]) -> tuple[int, list[int]] | None:
    """(d, ks) with every value == ks[i] / 10**d to the bit (the fewest decimals that do),
    or None."""
    for d in range(_MAX_DECIMALS + 1):
        p = 10**d
        ks: list[int] = []
        try:
            for v in values:
                k = round(v * p)
                if abs(k) >= 1 << 53 or k / p != v or not _is_positive_zero_or_nonzero(v):
                    break
                ks.append(k)
        except (OverflowError, ValueError):  # inf, nan
            return None
        if len(ks) == len(values):
            return d, ks
    return None


def _zigzag_deltas(ks: Sequence[int]) -> bytes:
    """Differences of `ks` (the first to 0), zigzag-coded, in the narrowest of 1/2/4/8 bytes
    (a width byte first)."""
    zz = [2 * d if d >= 0 else -2 * d - 1 for d in (b - a for a, b in pairwise((0, *ks)))]
    top = max(zz, default=0)
    for width, code in ((1, "B"), (2, "H"), (4, "I"), (8, "Q")):
        if top < 1 << (8 * width):
            return bytes([width]) + struct.pack(f"<{len(zz)}{code}", *zz)
    # Differences of 65 bits (values at both ends of int64): the values themselves.
    return bytes([_PLAIN]) + struct.pack(f"<{len(ks)}q", *ks)


def _undo_zigzag(payload: bytes, pos: int, m: int) -> tuple[list[int], int]:
    width = payload[pos]
    if width == _PLAIN:
        return list(struct.unpack_from(f"<{m}q", payload, pos + 1)), pos + 1 + 8 * m
    code = {1: "B", 2: "H", 4: "I", 8: "Q"}.get(width)
    if code is None:
        raise PackedError(f"a packed column has width {width}")
    zz = struct.unpack_from(f"<{m}{code}", payload, pos + 1)
    out: list[int] = []
    acc = 0
    for z in zz:
        acc += (z >> 1) if not z & 1 else -((z + 1) >> 1)
        out.append(acc)
    return out, pos + 1 + width * m


def _encode_column(kind: str, column: Sequence[Cell]) -> bytes:
    """One column: its kind, a null bitmap when it has nulls, its non-null values."""
    n = len(column)
    present = [v for v in column if v is not None]
    if not present:
        return bytes([_NULL])
    head = b""
    if len(present) < n:
        bitmap = bytearray((n + 7) // 8)
        for i, v in enumerate(column):
            if v is not None:
                bitmap[i >> 3] |= 1 << (i & 7)
        head = b"\x01" + bytes(bitmap)
    else:
        head = b"\x00"
    if kind == "i":
        return bytes([_INT]) + head + _zigzag_deltas([int(v) for v in present])
    if kind == "s":
        names: dict[float | str, int] = {}
        codes = bytearray()
        for v in present:
            codes.append(names.setdefault(v, len(names)))
            if len(names) > 255:
                raise PackedError("a text column has more than 255 distinct values in a block")
        table = b"".join(
            bytes([len(b)]) + b for b in (_text(name).encode() for name in names)
        )  # names are short (String(8))
        return bytes([_TEXT]) + head + bytes([len(names)]) + table + bytes(codes)
    floats = [float(v) for v in present]
    scaled = _decimal_ints(floats)
    if scaled is not None:
        d, ks = scaled
        return bytes([_DECIMAL]) + head + bytes([d]) + _zigzag_deltas(ks)
    m = len(floats)
    return bytes([_FLOAT]) + head + struct.pack(f"<{m}d", *floats)


def _text(name: float | str) -> str:
    """A name of a text column (checked once per name of a block, not per row)."""
    if not isinstance(name, str):
        raise TypeError(f"a text column holds {name!r}")
    return name


def _decode_column(payload: bytes, pos: int, n: int) -> tuple[Sequence[Cell], int]:
    kind = payload[pos]
    pos += 1
    if kind == _NULL:
        return [None] * n, pos
    has_nulls = payload[pos]
    pos += 1
    mask: bytes | None = None
    m = n
    if has_nulls:
        size = (n + 7) // 8
        mask = payload[pos : pos + size]
        if len(mask) != size:
            raise PackedError("a packed block is cut short")
        pos += size
        m = sum(bin(b).count("1") for b in mask)
    values: Sequence[Cell]
    if kind == _INT:
        values, pos = _undo_zigzag(payload, pos, m)
    elif kind == _DECIMAL:
        d = payload[pos]
        ks, pos = _undo_zigzag(payload, pos + 1, m)
        p = 10**d
        values = [k / p for k in ks]
    elif kind == _FLOAT:
        values = list(struct.unpack_from(f"<{m}d", payload, pos))
        pos += 8 * m
    elif kind == _TEXT:
        count = payload[pos]
        pos += 1
        names: list[str] = []
        for _ in range(count):
            size = payload[pos]
            names.append(payload[pos + 1 : pos + 1 + size].decode())
            pos += 1 + size
        values = [names[c] for c in payload[pos : pos + m]]
        pos += m
    else:
        raise PackedError(f"a packed column has kind {kind}")
    if len(values) != m:
        raise PackedError("a packed block is cut short")
    if mask is None:
        return values, pos
    out: list[Cell] = [None] * n
    it = iter(values)
    for i in range(n):
        if mask[i >> 3] >> (i & 7) & 1:
            out[i] = next(it)
    return out, pos


def pack_rows(series: Series, rows: Iterable[Values]) -> bytes:
    """Rows (values in column order, unit_id left out; keys unique) as one compressed block,
    sorted into key order.

    Layout 1, before compression, little-endian: the layout number (u8), the row count n (u32),
    the column count (u8), then each column in table order: its kind (u8: 0 all null, 1 decimal,
    2 float64, 3 int, 4 text); unless all null, a byte saying whether a null bitmap ((n + 7) //
    8 bytes, bit i set: row i has a value) follows; then the m non-null values: decimal: d (u8)
    and the k (value = k / 10**d) as zigzag differences; int: zigzag differences; differences
    are a width byte (1, 2, 4 or 8) and m unsigned ints of that width; float64: m doubles; text:
    the count of names (u8), each name (u8 length, UTF-8), and m u8 codes."""
    ordered = sorted(rows, key=itemgetter(*series.key))  # series.key_of, as one C call
    n = len(ordered)
    parts = [_HEADER.pack(_LAYOUT, n, len(series.columns))]
    columns = list(zip(*ordered, strict=True)) if ordered else [()] * len(series.columns)
    for kind, column in zip(series.kinds, columns, strict=True):
        parts.append(_encode_column(kind, column))
    return zlib.compress(b"".join(parts), _ZLIB_LEVEL)


def unpack_rows(series: Series, blob: bytes) -> list[Values]:
    """The rows of a block, in key order, values as stored."""
    try:
        payload = zlib.decompress(blob)
        layout, n, width = _HEADER.unpack_from(payload)
    except (zlib.error, struct.error) as exc:
        raise PackedError(f"a {series.name} block cannot be read: {exc}") from exc
    if width > len(series.columns):
        raise PackedError(f"a {series.name} block has {width} columns, more than the table")
    if layout != _LAYOUT:
        raise PackedError(f"a {series.name} block has layout {layout}; this version reads 1")
    pos = _HEADER.size
    columns: list[Sequence[Cell]] = []
    try:
        for _ in range(width):
            column, pos = _decode_column(payload, pos, n)
            columns.append(column)
    except (IndexError, struct.error) as exc:
        raise PackedError(f"a {series.name} block is cut short: {exc}") from exc
    if pos != len(payload):
        raise PackedError(f"a {series.name} block has bytes past its last column")
    # Columns added to the table after the block was packed read as null.
    columns += [[None] * n for _ in range(len(series.columns) - width)]
    return list(zip(*columns, strict=True))


def merge_rows(
    series: Series, stored: Sequence[Values], new: Iterable[Values]
) -> tuple[list[Values], list[Values]]:
    """`stored` with the rows of `new` whose key it lacks (the first of a repeated key wins);
    returns the merged rows and the rows added."""
    have = {series.key_of(r) for r in stored}
    added: list[Values] = []
    for r in new:
        k = series.key_of(r)
        if k not in have:
            have.add(k)
            added.append(r)
    return [*stored, *added], added


# -- writing late rows --------------------------------------------------------------------


def _lock_key_sql() -> str:
    return (
        "hashtextextended('eqgw-series-packing/' || current_database() || '/' || "
        "current_schema(), 0)"
    )


def may_be_packed(ts: float, now: float | None = None) -> bool:
    """Whether a row of time `ts` may belong to a block packed already (with half the
    horizon to spare for clocks that differ between gateways)."""
    now = time.time() if now is None else now
    return ts < now - PACK_AFTER_S / 2


def store_late_rows(
    conn: Connection, series: Series, rows: Sequence[R], ids: dict[UnitKey, int]
) -> tuple[Sequence[R], list[UnitValues]]:
    """The writer's rows of `series`: those of hours packed already are merged into their
    blocks here; the others are returned for the table's insert, with the rows the blocks
    gained as (unit_id, *values in column order), for the rollups. Inside the caller's
    transaction; live rows (newer than the horizon) cost nothing."""
    if not rows:
        return rows, []
    now = time.time()
    if not any(may_be_packed(values["ts"], now) for _, values in rows):
        return rows, []
    if conn.dialect.name == "postgresql":
        # Packing holds this exclusively: it waits for no writer, and no writer checks the
        # blocks halfway through a packing.
        conn.execute(text(f"SELECT pg_advisory_xact_lock_shared({_lock_key_sql()})"))
    spans: dict[int, list[float]] = {}
    for key, values in rows:
        uid, ts = ids[key], values["ts"]
        span = spans.get(uid)
        if span is None:
            spans[uid] = [ts, ts]
        else:
            span[0] = min(span[0], ts)
            span[1] = max(span[1], ts)
    packed = _packed_blocks(conn, series, spans)
    if not packed:
        return rows, []
    keep: list[R] = []
    late: dict[BlockKey, list[Values]] = {}
    # The block holds what SQLite's table would give back.
    sqlite = conn.dialect.name == "sqlite"
    cell = _as_sqlite_stores if sqlite else _cell
    rest = series.columns[1:]  # after ts
    for item in rows:
        key, values = item
        uid = ids[key]
        ts = values["ts"]
        start = block_start(ts)
        if (uid, start) in packed:
            if sqlite and ts == 0.0:
                ts = 0.0  # -0.0, as _as_sqlite_stores
            row: Values = (ts, *(cell(values.get(c)) for c in rest))
            late.setdefault((uid, start), []).append(row)
        else:
            keep.append(item)
    _drop_keys_in_table(conn, series, late)
    added = merge_into_blocks(conn, series, late)
    return keep, [(uid, *r) for uid, rows_added in added for r in rows_added]


def _cell(v: object) -> Cell:
    """A writer's value of a row packed late (its fields are JSON values): a number, a
    text or None, as a packed column holds."""
    if v is None or isinstance(v, float | int | str):
        return v
    raise TypeError(f"a packed column cannot hold {v!r}")


def _as_sqlite_stores(v: object) -> Cell:
    """A value as SQLite gives it back: a NaN is stored as NULL, -0.0 as 0 (an integral
    REAL is stored as an integer)."""
    if isinstance(v, float):
        if math.isnan(v):
            return None
        if v == 0.0:
            return 0.0
        return v
    return _cell(v)


def _drop_keys_in_table(
    conn: Connection, series: Series, late: dict[BlockKey, list[Values]]
) -> None:
    """Leave out of `late` the rows whose key the table holds (a row written while its hour
    was being packed, waiting for the next packing to fold it in): added to the block too,
    it would be counted twice."""
    t = series.rows
    names = [series.columns[i] for i in series.key]
    stmt = select(*(t.c[n] for n in names)).where(
        t.c.unit_id == bindparam("u"), t.c.ts.between(bindparam("lo"), bindparam("hi"))
    )
    for (uid, start), rows in list(late.items()):
        held = {
            r[0] if len(names) == 1 else tuple(r)
            for r in conn.execute(stmt, {"u": uid, "lo": start, "hi": start + BLOCK_S})
        }
        if held:
            late[(uid, start)] = [r for r in rows if series.key_of(r) not in held]


def pick(
    series: Series, rows: Sequence[UnitValues], columns: Sequence[str]
) -> list[tuple[Cell, ...]]:
    """(unit_id, *values) rows of `series` as tuples of `columns` (unit_id a column too)."""
    at = [0 if c == "unit_id" else 1 + series.columns.index(c) for c in columns]
    return [tuple(r[i] for i in at) for r in rows]


def _packed_blocks(
    conn: Connection, series: Series, spans: dict[int, list[float]]
) -> set[BlockKey]:
    b = series.blocks.c
    # A CoreTable's columns hold `object`s: these hold what the block models say.
    stmt = cast(
        "Select[int, float]",
        select(b.unit_id, b.ts).where(
            b.unit_id == bindparam("u"), b.ts.between(bindparam("lo"), bindparam("hi"))
        ),
    )
    found: set[BlockKey] = set()
    for uid, (lo, hi) in spans.items():
        for u, t in conn.execute(stmt, {"u": uid, "lo": block_start(lo), "hi": hi}):
            found.add((int(u), float(t)))
    return found


def merge_into_blocks(
    conn: Connection, series: Series, groups: dict[BlockKey, list[Values]]
) -> list[tuple[int, list[Values]]]:
    """Merge rows into their blocks (made when missing); returns per block the unit and the
    rows it gained. Blocks are locked while merged (PostgreSQL: FOR UPDATE, in key order;
    SQLite: the transaction's write lock)."""
    if not groups:
        return []
    keys = sorted(groups)
    stored = lock_blocks(conn, series.blocks, keys)
    inserts: list[BlockRow] = []
    updates: list[BlockRow] = []
    out: list[tuple[int, list[Values]]] = []
    for key in keys:
        blob = stored.get(key)
        old = unpack_rows(series, blob) if blob is not None else []
        merged, added = merge_rows(series, old, groups[key])
        if not added:
            continue
        out.append((key[0], added))
        row: BlockRow = {"u": key[0], "t": key[1], "n": len(merged), "d": pack_rows(series, merged)}
        (updates if blob is not None else inserts).append(row)
    save_blocks(conn, series.blocks, "samples", updates, inserts)
    return out


# -- packing the hours that are due --------------------------------------------------------


def compact(
    engine: Engine,
    *,
    now: float | None = None,
    after_s: float = PACK_AFTER_S,
    max_rows: int = COMPACT_ROWS,
    budget_s: float | None = None,
) -> int:
    """Pack the rows of hours that ended `after_s` before both `now` and their unit's newest
    data into blocks, `max_rows` a transaction; returns the rows packed. With `budget_s`, no
    transaction starts after that many seconds (the rest waits for the next call)."""
    now = time.time() if now is None else now
    if engine.dialect.name == "sqlite":
        engine = engine.execution_options(sqlite_begin="IMMEDIATE")
    began = time.monotonic()
    with engine.connect() as conn:
        edges = due_edges(conn, now, after_s)
    total = 0
    for series in SERIES:
        for uid, edge in edges.items():
            while True:
                if budget_s is not None and time.monotonic() - began >= budget_s:
                    return total
                with engine.begin() as conn:
                    n, more = compact_once(conn, series, uid, edge, max_rows)
                total += n
                if not more:
                    break
    return total


def due_edges(conn: Connection, now: float, after_s: float = PACK_AFTER_S) -> dict[int, float]:
    """Per unit with rows to pack, the block start before which its rows are packed."""
    u = _units.c
    edges: dict[int, float] = {}
    for uid, last in conn.execute(select(u.id, u.last_seen).where(u.last_seen.is_not(None))):
        edge = block_start(min(now, float(last)) - after_s)
        if math.isfinite(edge):
            edges[int(uid)] = edge
    due: dict[int, float] = {}
    for series in SERIES:
        t = series.rows
        probe = (
            select(t.c.ts).where(t.c.unit_id == bindparam("u"), t.c.ts < bindparam("e")).limit(1)
        )
        for uid, edge in edges.items():
            if uid not in due and conn.execute(probe, {"u": uid, "e": edge}).first() is not None:
                due[uid] = edge
    return due


def compact_once(
    conn: Connection, series: Series, unit_id: int, edge: float, max_rows: int
) -> tuple[int, bool]:
    """One transaction of `compact`: up to `max_rows` rows of a unit older than `edge` (a
    block start) moved from the table into their blocks. Returns (rows moved, whether more
    are due). On PostgreSQL one process packs at a time (an advisory lock, also taken shared
    by writers storing rows this old; a packer that cannot have it skips its turn)."""
    if conn.dialect.name == "postgresql":
        mine = conn.execute(
            text(f"SELECT pg_try_advisory_xact_lock({_lock_key_sql()})")
        ).scalar_one()
        if not mine:
            return 0, False
    t = series.rows
    order = [t.c[series.columns[i]] for i in series.key]
    rows = conn.execute(
        select(*(t.c[c] for c in series.columns))
        .where(t.c.unit_id == unit_id, t.c.ts < edge)
        .order_by(*order)
        .limit(max_rows + 1)
    ).all()
    if not rows:
        return 0, False
    more = len(rows) > max_rows
    values = [tuple(r) for r in rows]
    if more:
        values = values[:max_rows]
        # The last hour read may go on past the limit: it is packed whole next time.
        last = block_start(values[-1][0])
        whole = [r for r in values if block_start(r[0]) != last]
        values = whole or values
    groups: dict[BlockKey, list[Values]] = {}
    for r in values:
        groups.setdefault((unit_id, block_start(r[0])), []).append(r)
    merge_into_blocks(conn, series, groups)
    _delete_rows(conn, series, unit_id, values)
    return len(values), more


def _delete_rows(conn: Connection, series: Series, unit_id: int, rows: list[Values]) -> None:
    """Delete the table's rows of `unit_id` with the keys of `rows`."""
    names = [series.columns[i] for i in series.key]
    if conn.dialect.name == "postgresql":
        cols = [[r[i] for r in rows] for i in series.key]
        types = ["float8" if series.kinds[i] == "f" else "int8" for i in series.key]
        unnest = ", ".join(f"CAST(:k{i} AS {ty}[])" for i, ty in enumerate(types))
        match = " AND ".join(f"r.{n} = k.c{i}" for i, n in enumerate(names))
        aliases = ", ".join(f"c{i}" for i in range(len(names)))
        conn.execute(
            text(
                f"DELETE FROM {series.name} r USING unnest({unnest}) AS k({aliases}) "
                f"WHERE r.unit_id = :u AND {match}"
            ),
            {"u": unit_id, **{f"k{i}": pg_array(c) for i, c in enumerate(cols)}},
        )
        return
    raw = conn.connection.driver_connection
    assert raw is not None
    where = " AND ".join(f"{n} = ?" for n in names)
    params = [(unit_id, *(r[i] for i in series.key)) for r in rows]
    raw.executemany(f"DELETE FROM {series.name} WHERE unit_id = ? AND {where}", params)


# -- reading --------------------------------------------------------------------------------


def read_rows(
    conn: Connection,
    series: Series,
    unit_id: int,
    start: float,
    end: float,
    *,
    keep: Callable[[Values], bool] | None = None,
    limit: int | None = None,
) -> list[Values]:
    """The packed rows of a unit with start <= ts < end (and `keep(row)`), in key order
    (values in column order). With `limit`, blocks are read in time order until at least
    `limit` rows are found (the first `limit` rows of the range are among them)."""
    if not start < end:
        return []
    b = series.blocks.c
    stmt = cast(  # a CoreTable's columns hold `object`s: `data` holds bytes
        "Select[bytes]",
        select(b.data)
        .where(b.unit_id == unit_id, b.ts >= block_start(start), b.ts < end)
        .order_by(b.ts),
    )
    out: list[Values] = []
    for (blob,) in conn.execute(stmt):
        out += [
            r
            for r in unpack_rows(series, bytes(blob))
            if start <= r[0] < end and (keep is None or keep(r))
        ]
        if limit is not None and len(out) >= limit:
            break
    return out


def packed_counts(conn: Connection) -> dict[str, int]:
    """Rows held in blocks, per row table."""
    return {
        s.name: int(
            conn.execute(
                cast("Select[int]", select(func.coalesce(func.sum(s.blocks.c.samples), 0)))
            ).scalar_one()
        )
        for s in SERIES
    }
