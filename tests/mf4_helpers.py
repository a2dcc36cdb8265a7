"""MF4 files for the salvage tests: python-can's MF4Writer output, and the same frames laid out
as a CANedge writes them (directory first, one unsorted data group with record ids, data in
DZ blocks after it), built from asammdf's own blocks."""

from __future__ import annotations

import struct
from collections.abc import Sequence
from pathlib import Path

import can

from eqgw.bus import mf4

_COMMON = struct.Struct("<4s4xQQ")


def write_python_can_mf4(path: Path, frames: Sequence[can.Message], level: int = 0) -> None:
    """`frames` written by python-can's MF4Writer (compression 0 none, 1 deflate, 2
    transposed deflate)."""
    mf4.load()  # python-can's MF4 module runs without asammdf until asked (eqgw.bus.mf4)
    with can.Logger(str(path), compression_level=level) as writer:
        for msg in frames:
            writer.on_message_received(msg)


def _blocks(data: bytes) -> dict[int, tuple[bytes, int, int]]:
    """Every block of a file written whole that the header leads to: address -> (id, length,
    links)."""
    out: dict[int, tuple[bytes, int, int]] = {}
    todo = [64]
    while todo:
        address = todo.pop()
        if address in out:
            continue
        bid, length, links = _COMMON.unpack_from(data, address)
        out[address] = (bid, length, links)
        todo.extend(a for a in struct.unpack_from(f"<{links}Q", data, address + 24) if a)
    return out


def canedge_style(
    source: Path,
    path: Path,
    *,
    block_bytes: int = 4096,
    zipped: bool = True,
    unfinalized: bool = False,
) -> None:
    """Re-lay python-can's MF4 `source` as a CANedge lays its files out: ID, header, the
    whole directory (one data group, its channel groups with record ids 1, 2, 3), then the
    records of every group interleaved in time order, each after its 1-byte record id, in
    data blocks of `block_bytes` (DZ deflate blocks listed by a DL when `zipped`, else one DT
    block). `unfinalized`: the identification says "UnFinMF", the cycle counters are 0 and
    the DT block's length was never written (a logger still recording)."""
    from asammdf.blocks import v4_constants as v4c
    from asammdf.blocks.v4_blocks import (
        ChannelGroup,
        DataBlock,
        DataGroup,
        DataList,
        DataZippedBlock,
        HeaderBlock,
    )

    data = bytearray(source.read_bytes())
    blocks = _blocks(bytes(data))
    with source.open("rb") as f:
        size = len(data)
        header = HeaderBlock(address=64, stream=f, file_limit=size)
        dgs = []
        address = header.first_dg_addr
        while address:
            dgs.append(DataGroup(address=address, stream=f, file_limit=size))
            address = dgs[-1].next_dg_addr
        cgs = [
            ChannelGroup(address=dg.first_cg_addr, stream=f, file_limit=size, si_map={})
            for dg in dgs
        ]
        records: list[tuple[float, int, bytes]] = []
        for rid, (dg, cg) in enumerate(zip(dgs, cgs, strict=True), start=1):
            if not dg.data_block_addr:
                continue
            assert blocks[dg.data_block_addr][0] == b"##DT", "write the source with level 0"
            raw = DataBlock(address=dg.data_block_addr, stream=f, file_limit=size).data
            n = cg.samples_byte_nr + cg.invalidation_bytes_nr
            for i in range(0, len(raw), n):
                record = bytes(raw[i : i + n])
                records.append((struct.unpack_from("<d", record)[0], rid, record))
    records.sort(key=lambda r: r[0])  # stable: equal times keep each group's order
    stream = b"".join(bytes([rid]) + record for _, rid, record in records)

    # The directory: every block but the data, the DL and the data groups after the first.
    data_ids = {b"##DT", b"##DL", b"##DZ"}
    dropped = {dg.address for dg in dgs[1:]}
    keep = [a for a, (bid, _, _) in sorted(blocks.items()) if bid not in data_ids]
    keep = [a for a in keep if a not in dropped and a != 64]
    new_address: dict[int, int] = {64: 64}
    cursor = 64 + blocks[64][1] + (-blocks[64][1] % 8)
    for a in keep:
        new_address[a] = cursor
        length = blocks[a][1]
        cursor += length + (-length % 8)
    out = bytearray(data[:64])
    for a in [64, *keep]:
        _, length, links = blocks[a]
        block = bytearray(data[a : a + length])
        for i in range(links):
            (link,) = struct.unpack_from("<Q", block, 24 + 8 * i)
            struct.pack_into("<Q", block, 24 + 8 * i, new_address.get(link, 0))
        out += block + bytes(-length % 8)
    # One data group holding every channel group, unsorted with 1-byte record ids.
    dg0 = new_address[dgs[0].address]
    struct.pack_into("<B", out, dg0 + 24 + 8 * 4, 1)
    for rid, cg in enumerate(cgs, start=1):
        at = new_address[cg.address]
        nxt = new_address[cgs[rid].address] if rid < len(cgs) else 0
        struct.pack_into("<Q", out, at + 24, nxt)
        struct.pack_into("<Q", out, at + 24 + 8 * 6, rid)  # record id
        if unfinalized:
            struct.pack_into("<Q", out, at + 24 + 8 * 7, 0)  # cycle counter never written
    pieces = [stream[i : i + block_bytes] for i in range(0, len(stream), block_bytes)]
    if zipped:
        dl_at = len(out)
        count = len(pieces)
        dl_len = 24 + 8 * (count + 1) + 8 + 8 * count  # links, flags/count, offsets
        first = dl_at + dl_len + (-dl_len % 8)
        zipped_blocks = [
            bytes(DataZippedBlock(data=p, zip_type=v4c.FLAG_DZ_DEFLATE, original_type=b"DT"))
            for p in pieces
        ]
        addresses = []
        at = first
        for z in zipped_blocks:
            addresses.append(at)
            at += len(z) + (-len(z) % 8)
        kwargs: dict[str, int] = {"links_nr": count + 1, "next_dl_addr": 0, "flags": 0}
        offset = 0
        for i, (a, p) in enumerate(zip(addresses, pieces, strict=True)):
            kwargs[f"data_block_addr{i}"] = a
            kwargs[f"offset_{i}"] = offset
            offset += len(p)
        dl = bytes(DataList(**kwargs))  # type: ignore[arg-type]
        assert len(dl) == dl_len, (len(dl), dl_len)
        struct.pack_into("<Q", out, dg0 + 24 + 16, dl_at)
        out += dl + bytes(-len(dl) % 8)
        for z in zipped_blocks:
            out += z + bytes(-len(z) % 8)
    else:
        struct.pack_into("<Q", out, dg0 + 24 + 16, len(out))
        dt = bytearray(bytes(DataBlock(data=stream)))
        if unfinalized:
            struct.pack_into("<Q", dt, 8, 24)  # the length a logger writes when it starts
        out += dt
    if unfinalized:
        out[0:8] = b"UnFinMF "
        flags = v4c.FLAG_UNFIN_UPDATE_CG_COUNTER
        if not zipped:
            flags |= v4c.FLAG_UNFIN_UPDATE_LAST_DT_LENGTH
        struct.pack_into("<H", out, 60, flags)
    path.write_bytes(bytes(out))
