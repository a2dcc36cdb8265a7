"""Rows of packed blocks, shared by the raw archive (`raw_blocks`) and the packed series
(`measurement_blocks`, `battery_blocks`): each table has (unit_id, ts) as its key, a count
column and `data`. Locking the stored blocks of a merge and writing the merged ones back is
the same for all of them."""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from typing import TYPE_CHECKING, TypedDict, cast

from sqlalchemy import Connection, bindparam, select, text

if TYPE_CHECKING:
    from sqlalchemy import Select

    from eqgw.store.models import CoreTable

BlockKey = tuple[int, float]  # (unit id, block start)


class BlockRow(TypedDict):
    """A merged block to write back (`save_blocks`)."""

    u: int  # unit id
    t: float  # block start
    n: int  # its count (frames, rows)
    d: bytes  # its packed bytes


def start_of(ts: float, width_s: float) -> float:
    """The start of the block `width_s` wide holding `ts`: start <= ts < start + width_s."""
    start = math.floor(ts / width_s) * width_s
    # ts / width_s rounds: a time a hair below a boundary can land on the next block.
    if start > ts:
        start -= width_s
    elif ts >= start + width_s:
        start += width_s
    return start


def pg_array(values: Iterable[object]) -> str:
    """A PostgreSQL array literal of numbers or of plain names (no quoting needed), sent as
    one text parameter: the driver's list adaptation costs microseconds per element. str() of
    a float is its repr, the shortest text that reads back to the same bits."""
    return "{" + ",".join(map(str, values)) + "}"


def lock_blocks(
    conn: Connection, table: CoreTable, keys: Sequence[BlockKey]
) -> dict[BlockKey, bytes]:
    """The stored blocks of `table` among `keys` (sorted), locked until the transaction ends:
    PostgreSQL FOR UPDATE in key order (writers lock in the same order) in one query; SQLite
    one range read per unit (the transaction's write lock holds them)."""
    out: dict[BlockKey, bytes] = {}
    if conn.dialect.name == "postgresql":
        name = table.name.replace('"', '""')
        result = conn.execute(
            text(
                f'SELECT b.unit_id, b.ts, b.data FROM "{name}" b JOIN unnest('
                "CAST(:u AS int[]), CAST(:t AS float8[])) AS k(u, t) "
                "ON b.unit_id = k.u AND b.ts = k.t ORDER BY b.unit_id, b.ts FOR UPDATE OF b"
            ),
            {"u": pg_array(k[0] for k in keys), "t": pg_array(k[1] for k in keys)},
        )
        for u, t, d in result:
            out[(int(u), float(t))] = bytes(d)
        return out
    wanted = set(keys)
    per_unit: dict[int, list[float]] = {}
    for uid, start in keys:
        per_unit.setdefault(uid, []).append(start)
    c = table.c
    # A CoreTable's columns hold `object`s: these hold what every block table's model says.
    stmt = cast(
        "Select[int, float, bytes]",
        select(c.unit_id, c.ts, c.data).where(
            c.unit_id == bindparam("u"), c.ts.between(bindparam("lo"), bindparam("hi"))
        ),
    )
    for uid, starts in per_unit.items():
        for u, t, d in conn.execute(stmt, {"u": uid, "lo": min(starts), "hi": max(starts)}):
            if (u, t) in wanted:
                out[(int(u), float(t))] = bytes(d)
    return out


def save_blocks(
    conn: Connection,
    table: CoreTable,
    count_column: str,
    updates: Sequence[Mapping[str, object]],
    inserts: Sequence[Mapping[str, object]],
) -> None:
    """Write merged blocks back: `updates` replace stored ones, `inserts` are new; each row
    a `BlockRow`."""
    c = table.c
    if updates:
        conn.execute(
            table.update()
            .where(c.unit_id == bindparam("u"), c.ts == bindparam("t"))
            .values({count_column: bindparam("n"), "data": bindparam("d")}),
            updates,
        )
    if inserts:
        conn.execute(
            table.insert().values(
                {
                    "unit_id": bindparam("u"),
                    "ts": bindparam("t"),
                    count_column: bindparam("n"),
                    "data": bindparam("d"),
                }
            ),
            inserts,
        )
