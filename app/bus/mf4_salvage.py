"""The frames of an MF4 (ASAM MDF 4) CAN log cut short, e.g. a CANedge's SD card after a power
cut: every complete record before the cut, read block by block.

asammdf opens a file through its block directory (data groups, channel groups, channels) and
refuses one where a block the directory points to is cut off. This reader walks the same
blocks itself and keeps what is whole:

- asammdf's block classes (`asammdf.blocks.v4_blocks`: `FileIdentificationBlock`,
  `HeaderBlock`, `DataGroup`, `ChannelGroup`, `Channel`, `DataList`, `HeaderList`,
  `DataBlock`, `DataZippedBlock`) read every block that lies whole in the file, and
  `asammdf.blocks.v4_constants` names the block fields' values. They are only ever handed
  blocks checked to end inside the file: on a cut block they log a warning and return an
  empty default block instead of raising.
- What no asammdf class reads is read here: the bytes of the one data block the cut goes
  through (a `##DT` up to the cut; a `##DZ` with plain deflate decompressed as far as its
  bytes go; a transposed `##DZ` cut short holds no whole record and is lost), and the records
  themselves (fixed-size records of a sorted data group, or record-id-prefixed records of an
  unsorted one, as a CANedge writes them), decoded from the channels' byte and bit offsets.
- Where the directory itself is cut off (asammdf, and so python-can's `MF4Writer`, writes the
  data blocks first and the directory after them, so any cut in the data loses it), the data
  blocks are found by walking the file block after block from the header, and their records
  are read in the layout python-can's `MF4Writer` gives its `CAN_DataFrame` group (84 bytes:
  time, bus channel, id, IDE, DLC, data length, 64 data bytes, Dir, EDL, BRS, ESI). That
  layout is only assumed for a file asammdf wrote (its identification block says so) whose
  first data block holds 84-byte records, and every record is checked against it (flags 0 or
  1, at most 64 data bytes, a finite time): reading stops at the first that does not fit.

The last record the cut goes through is dropped and counted (`partial_records`).
"""

from __future__ import annotations

import contextlib
import dataclasses
import heapq
import io
import logging
import math
import os
import struct
import zlib
from collections.abc import Generator, Iterator
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import can

log = logging.getLogger(__name__)

_COMMON = struct.Struct("<4s4xQQ")  # block id, length, link count
_DZ_COMMON = struct.Struct("<4s4xQQ2sBxIQQ")  # + original type, zip type, param, sizes
_DATA_IDS = (b"##DT", b"##DZ")
# The CAN_DataFrame fields a frame is made of (the names' last part: "CAN_DataFrame.ID").
_FIELDS = ("BusChannel", "ID", "IDE", "DLC", "DataLength", "DataBytes", "Dir", "EDL", "BRS", "ESI")
_KINDS = {"CAN_DataFrame": "data", "CAN_RemoteFrame": "remote", "CAN_ErrorFrame": "error"}
_MAX_BLOCKS = 1_000_000  # a walk of the block graph stops here (a corrupt file's loops)
_MAX_GAP = 256  # zero bytes between two blocks a walk steps over


class Mf4SalvageError(Exception):
    """Nothing of the file can be recovered (not an MF4, no usable layout, no data)."""


@dataclasses.dataclass(frozen=True, slots=True)
class Field:
    """Where one value sits in a record: byte offset (record id excluded), bits, data type."""

    byte_offset: int
    bit_offset: int
    bit_count: int
    data_type: int


@dataclasses.dataclass(slots=True)
class RecordLayout:
    """One channel group's record: its size, its id in an unsorted group, its CAN fields."""

    record_id: int
    size: int  # data bytes + invalidation bytes
    kind: str | None  # "data", "remote", "error"; None: a group that holds no frames
    time: Field | None = None
    time_conversion: Any = None  # asammdf ChannelConversion of the master channel, if any
    fields: dict[str, Field] = dataclasses.field(default_factory=dict)
    vlsd: bool = False  # variable-length records (u32 length first)


# python-can's MF4Writer CAN_DataFrame record, for a file whose directory is cut off.
PYTHON_CAN_LAYOUT = RecordLayout(
    record_id=0,
    size=84,
    kind="data",
    time=Field(0, 0, 64, 4),
    fields={
        "BusChannel": Field(8, 0, 8, 0),
        "ID": Field(9, 0, 32, 0),
        "IDE": Field(13, 0, 8, 0),
        "DLC": Field(14, 0, 8, 0),
        "DataLength": Field(15, 0, 8, 0),
        "DataBytes": Field(16, 0, 512, 10),
        "Dir": Field(80, 0, 8, 0),
        "EDL": Field(81, 0, 8, 0),
        "BRS": Field(82, 0, 8, 0),
        "ESI": Field(83, 0, 8, 0),
    },
)


@contextlib.contextmanager
def quiet_asammdf() -> Iterator[None]:
    """asammdf logs (at WARNING) what it finds odd in a block; the salvage says it in one line."""
    logger = logging.getLogger("asammdf")
    level = logger.level
    logger.setLevel(logging.CRITICAL)
    try:
        yield
    finally:
        logger.setLevel(level)


def _header(f: io.BufferedReader, address: int, size: int) -> tuple[bytes, int, int] | None:
    """(id, length, link count) of the block at `address`, None when its header is cut off."""
    if address <= 0 or address + _COMMON.size > size:
        return None
    f.seek(address)
    bid, length, links = _COMMON.unpack(f.read(_COMMON.size))
    return bid, length, links


def _whole(f: io.BufferedReader, address: int, size: int) -> bool:
    head = _header(f, address, size)
    return head is not None and head[1] >= _COMMON.size and address + head[1] <= size


def find_cut(path: str | os.PathLike[str]) -> str | None:
    """Why an MF4 file is cut short (a block its header leads to ends past the end of the
    file), or None when every block it links is whole (or it is no MF4 at all)."""
    size = os.path.getsize(path)
    with open(path, "rb") as f:
        ident = f.read(64)
        if len(ident) < 64 or not ident.startswith((b"MDF     ", b"UnFinMF ")):
            return None
        if not ident[8:12].startswith(b"4"):
            return None
        if size < 64 + 104:
            return f"the file ends at byte {size}, inside its header"
        seen: set[int] = set()
        todo = [64]
        while todo and len(seen) < _MAX_BLOCKS:
            address = todo.pop()
            if address in seen:
                continue
            seen.add(address)
            head = _header(f, address, size)
            if head is None:
                return f"a block at byte {address} lies past the end of the file ({size} bytes)"
            bid, length, links = head
            if not bid.startswith(b"##") or length < _COMMON.size:
                return None  # not a block: leave the verdict to asammdf
            if address + length > size:
                return (
                    f"the {bid[2:].decode(errors='replace')} block at byte {address} needs "
                    f"{length} bytes, the file ends {size - address} bytes into it"
                )
            if links and address + _COMMON.size + 8 * links <= size:
                f.seek(address + _COMMON.size)
                raw = f.read(8 * links)
                todo.extend(a for a in struct.unpack(f"<{links}Q", raw) if a)
    return None


@dataclasses.dataclass(slots=True)
class _Chunk:
    """Bytes of one data block (decompressed) and whether the block was whole."""

    data: bytes
    whole: bool
    lost_bytes: int = 0  # of a compressed block cut short that holds no whole record


class Mf4Salvage:
    """The complete records of a truncated MF4 file as python-can messages.

    Built by `open()`; iterate it for the frames (time order). After iteration: `frames`,
    `partial_records`, `lost_records`, `last_timestamp`, `summary()`.
    """

    def __init__(self, path: str | os.PathLike[str], cut: str) -> None:
        self.path = Path(path)
        self.cut = cut
        self.size = os.path.getsize(path)
        self.start_timestamp = 0.0
        self.unfinalized_flags = 0
        self.layout_source = "the file's channel groups"
        self.frames = 0
        self.partial_records = 0
        self.lost_records = 0
        self.last_timestamp: float | None = None
        # (layout per record id, record-id length, data chunks) of each data group
        self._groups: list[tuple[dict[int, RecordLayout], int, list[_Chunk]]] = []

    # -- reading the directory -----------------------------------------------------------

    @classmethod
    def open(cls, path: str | os.PathLike[str], cut: str) -> Mf4Salvage:
        """Read the directory and the data blocks that survive; Mf4SalvageError when there is
        nothing to recover from."""
        from asammdf.blocks.v4_blocks import FileIdentificationBlock, HeaderBlock

        self = cls(path, cut)
        with quiet_asammdf(), open(path, "rb") as f:
            ident = FileIdentificationBlock(stream=f)
            self.unfinalized_flags = int(ident.unfinalized_standard_flags)
            if not _whole(f, 64, self.size):
                raise Mf4SalvageError("the file is cut off inside its header block")
            # The header's comment block may be past the cut: read the header from a copy
            # without it (asammdf's HeaderBlock reads the comment, and raises on a cut one).
            f.seek(64)
            raw = bytearray(f.read(104))
            struct.pack_into("<Q", raw, 24 + 5 * 8, 0)
            header = HeaderBlock(address=0, stream=io.BytesIO(bytes(raw)), file_limit=len(raw))
            self.start_timestamp = header.start_time.timestamp()
            try:
                self._read_directory(f, header.first_dg_addr)
            except Mf4SalvageError as exc:
                program = bytes(ident.program_identification)
                if not program.startswith(b"amdf"):
                    raise Mf4SalvageError(f"{exc}: no record layout to read the data by") from exc
                self.layout_source = "python-can's MF4Writer layout (the directory is cut off)"
                chunks = self._walk_data_blocks(f)
                if not chunks:
                    raise Mf4SalvageError(f"{exc}, and no data block is before the cut") from exc
                self._groups = [({0: PYTHON_CAN_LAYOUT}, 0, chunks)]
        if not any(chunks for _, _, chunks in self._groups):
            raise Mf4SalvageError("no data block before the cut")
        return self

    def _read_directory(self, f: io.BufferedReader, dg_addr: int) -> None:
        from asammdf.blocks.v4_blocks import ChannelGroup, DataGroup

        seen: set[int] = set()
        while dg_addr:
            if dg_addr in seen:
                break
            seen.add(dg_addr)
            if not _whole(f, dg_addr, self.size):
                if not self._groups:
                    raise Mf4SalvageError("the channel directory is cut off")
                break  # later data groups are past the cut
            dg = DataGroup(address=dg_addr, stream=f, file_limit=self.size)
            layouts: dict[int, RecordLayout] = {}
            cg_addr = dg.first_cg_addr
            while cg_addr:
                if not _whole(f, cg_addr, self.size):
                    raise Mf4SalvageError("a channel group block is cut off")
                cg = ChannelGroup(address=cg_addr, stream=f, file_limit=self.size, si_map={})
                layouts[cg.record_id] = self._layout(f, cg)
                cg_addr = cg.next_cg_addr
            if any(layout.kind for layout in layouts.values()):
                chunks = self._data_chain(f, dg.data_block_addr, layouts, dg.record_id_len)
                self._groups.append((layouts, dg.record_id_len, chunks))
            dg_addr = dg.next_dg_addr
        if not self._groups:
            raise Mf4SalvageError("no CAN frame channel group in the directory")

    def _layout(self, f: io.BufferedReader, cg: Any) -> RecordLayout:
        from asammdf.blocks import v4_constants as v4c

        layout = RecordLayout(
            record_id=cg.record_id,
            size=cg.samples_byte_nr + cg.invalidation_bytes_nr,
            kind=None,
            vlsd=bool(cg.flags & v4c.FLAG_CG_VLSD),
        )
        for ch in self._channels(f, cg.first_ch_addr, depth=0):
            name = str(ch.name)
            field = Field(ch.byte_offset, ch.bit_offset, ch.bit_count, ch.data_type)
            if ch.channel_type == v4c.CHANNEL_TYPE_MASTER and ch.sync_type == v4c.SYNC_TYPE_TIME:
                layout.time, layout.time_conversion = field, ch.conversion
            elif name in _KINDS:
                layout.kind = _KINDS[name]
            elif "." in name and name.rsplit(".", 1)[0] in _KINDS:
                part = name.rsplit(".", 1)[1]
                if part in _FIELDS and ch.channel_type == v4c.CHANNEL_TYPE_VALUE:
                    layout.fields[part] = field
        if layout.kind is not None and (layout.time is None or "ID" not in layout.fields):
            layout.kind = None  # a frame group without time or id: not ours to read
        if layout.kind == "data" and "DataBytes" not in layout.fields:
            layout.kind = None  # data bytes stored apart (VLSD): not read here
        return layout

    def _channels(self, f: io.BufferedReader, cn_addr: int, depth: int) -> Iterator[Any]:
        from asammdf.blocks.v4_blocks import Channel

        seen: set[int] = set()
        while cn_addr and cn_addr not in seen and depth < 4:
            seen.add(cn_addr)
            if not _whole(f, cn_addr, self.size):
                raise Mf4SalvageError("a channel block is cut off")
            ch = Channel(
                address=cn_addr,
                stream=f,
                mapped=False,
                file_limit=self.size,
                parsed_strings=None,
                use_display_names=False,
                cc_map={},
                si_map={},
                at_map={},
            )
            yield ch
            if ch.component_addr and _peek_id(f, ch.component_addr, self.size) == b"##CN":
                yield from self._channels(f, ch.component_addr, depth + 1)
            cn_addr = ch.next_ch_addr

    # -- reading the data blocks ---------------------------------------------------------

    def _data_chain(
        self, f: io.BufferedReader, address: int, layouts: dict[int, RecordLayout], id_len: int
    ) -> list[_Chunk]:
        """The data of one data group: a DT/DZ block, or the blocks of its DL (HL) lists."""
        from asammdf.blocks.v4_blocks import HeaderList

        chunks: list[_Chunk] = []
        bid = _peek_id(f, address, self.size)
        if bid == b"##HL":
            if not _whole(f, address, self.size):
                return chunks
            address = HeaderList(address=address, stream=f, file_limit=self.size).first_dl_addr
            bid = _peek_id(f, address, self.size)
        if bid in _DATA_IDS:
            chunk = self._data_block(f, address, last=True)
            if chunk is not None:
                chunks.append(chunk)
            return chunks
        seen: set[int] = set()
        while bid == b"##DL" and address not in seen:
            seen.add(address)
            links = self._list_links(f, address)
            if links is None:
                break
            next_dl, blocks = links
            for i, block in enumerate(blocks):
                if not block:
                    break
                chunk = self._data_block(f, block, last=not next_dl and i == len(blocks) - 1)
                if chunk is None:
                    return chunks
                chunks.append(chunk)
                if not chunk.whole:
                    return chunks
            address = next_dl
            bid = _peek_id(f, address, self.size) if address else None
        return chunks

    def _list_links(self, f: io.BufferedReader, address: int) -> tuple[int, list[int]] | None:
        """(next DL, data block addresses) of a DL block: asammdf's DataList for a whole
        block; the links before the cut of one cut off."""
        from asammdf.blocks.v4_blocks import DataList

        if _whole(f, address, self.size):
            dl = DataList(address=address, stream=f, file_limit=self.size)
            count = dl.links_nr - 1
            return dl.next_dl_addr, [int(getattr(dl, f"data_block_addr{i}")) for i in range(count)]
        head = _header(f, address, self.size)
        if head is None:
            return None
        present = min(head[2], (self.size - address - _COMMON.size) // 8)
        if present < 1:
            return None
        f.seek(address + _COMMON.size)
        links = struct.unpack(f"<{present}Q", f.read(8 * present))
        return 0, [a for a in links[1:] if a + _COMMON.size <= self.size]

    def _data_block(self, f: io.BufferedReader, address: int, *, last: bool) -> _Chunk | None:
        """One DT or DZ block's bytes: asammdf's classes read a whole one, the bytes up to the
        cut of one cut off are read here."""
        from asammdf.blocks import v4_constants as v4c
        from asammdf.blocks.v4_blocks import DataBlock, DataZippedBlock

        head = _header(f, address, self.size)
        if head is None:
            return None
        bid, length, _ = head
        if bid == b"##DT":
            stale = bool(self.unfinalized_flags & v4c.FLAG_UNFIN_UPDATE_LAST_DT_LENGTH) and last
            if address + length <= self.size and not stale:
                return _Chunk(
                    bytes(DataBlock(address=address, stream=f, file_limit=self.size).data), True
                )
            # Cut off (or an unfinalized file's last block, whose length was never written):
            # its bytes up to the end of the file.
            f.seek(address + _COMMON.size)
            return _Chunk(f.read(self.size - address - _COMMON.size), stale)
        if bid == b"##DZ":
            if address + _DZ_COMMON.size > self.size:
                return None
            if address + length <= self.size:
                dz = DataZippedBlock(address=address, stream=f, file_limit=self.size)
                return _Chunk(bytes(dz.data), True)
            f.seek(address)
            _, _, _, original_type, zip_type, _, original_size, _ = _DZ_COMMON.unpack(
                f.read(_DZ_COMMON.size)
            )
            if original_type != b"DT":
                return None
            if zip_type == v4c.FLAG_DZ_DEFLATE:
                # Deflate is a stream: the bytes before the cut give the data up to there.
                unzip = zlib.decompressobj()
                data = unzip.decompress(f.read(self.size - address - _DZ_COMMON.size))
                return _Chunk(data, False)
            # Transposed (or another algorithm): nothing whole before the cut.
            return _Chunk(b"", False, lost_bytes=original_size)
        return None

    def _walk_data_blocks(self, f: io.BufferedReader) -> list[_Chunk]:
        """The data blocks of python-can's CAN_DataFrame group, found by walking the blocks
        from the header on: the first data block, and the ones after it as long as each
        before was full (asammdf splits a group's data into blocks of one size; a shorter
        block, or a DL, ends the group)."""
        chunks: list[_Chunk] = []
        first_size: int | None = None
        for address, bid, length in self._walk(f):
            if bid not in _DATA_IDS:
                if chunks:
                    break  # the group's data ends (its DL, or the directory)
                continue
            original, fits = self._python_can_block(f, address, length)
            if first_size is None:
                if not fits:
                    raise Mf4SalvageError("its records are not python-can's MF4Writer's")
                first_size = original
            elif not fits or original > first_size:
                break
            chunk = self._data_block(f, address, last=False)
            if chunk is None:
                break
            chunks.append(chunk)
            if not chunk.whole or original < first_size:
                break
        return chunks

    def _walk(self, f: io.BufferedReader) -> Iterator[tuple[int, bytes, int]]:
        """(address, id, length) of the blocks one after the other from the header, over the
        zero bytes asammdf leaves between some of them, up to the cut."""
        address = 64
        while address + _COMMON.size <= self.size:
            head = _header(f, address, self.size)
            assert head is not None
            bid, length, _ = head
            if not bid.startswith(b"##") or length < _COMMON.size:
                f.seek(address)
                gap = f.read(_MAX_GAP)
                found = gap.find(b"##", 1)
                while found > 0 and found % 8:
                    found = gap.find(b"##", found + 1)
                if found <= 0:
                    return
                address += found
                continue
            yield address, bid, length
            address += length + (-length % 8)

    def _python_can_block(
        self, f: io.BufferedReader, address: int, length: int
    ) -> tuple[int, bool]:
        """(data bytes, whether they are 84-byte records) of a DT or DZ block."""
        from asammdf.blocks import v4_constants as v4c

        original = length - _COMMON.size
        fits = True
        if _peek_id(f, address, self.size) == b"##DZ":
            if address + _DZ_COMMON.size > self.size:
                return 0, False
            f.seek(address)
            _, _, _, original_type, zip_type, param, original, _ = _DZ_COMMON.unpack(
                f.read(_DZ_COMMON.size)
            )
            fits = original_type == b"DT" and (
                zip_type != v4c.FLAG_DZ_TRANSPOSED_DEFLATE or param == PYTHON_CAN_LAYOUT.size
            )
        return original, fits and original % PYTHON_CAN_LAYOUT.size == 0

    # -- decoding ------------------------------------------------------------------------

    def __iter__(self) -> Iterator[can.Message]:
        streams = [self._group_messages(*group) for group in self._groups]
        merged = streams[0] if len(streams) == 1 else heapq.merge(*streams, key=_ts)
        for msg in merged:
            self.frames += 1
            self.last_timestamp = msg.timestamp
            yield msg

    def _group_messages(
        self, layouts: dict[int, RecordLayout], id_len: int, chunks: list[_Chunk]
    ) -> Iterator[can.Message]:
        # Records may span block boundaries: the group's blocks are one byte stream.
        rest = b""
        for chunk in chunks:
            if chunk.lost_bytes:
                self.lost_records += _records_in(chunk.lost_bytes, layouts, id_len)
            buf = rest + chunk.data
            if id_len == 0:
                layout = next(iter(layouts.values()))
                n = len(buf) // layout.size if layout.size else 0
                yield from self._decode(layout, buf[: n * layout.size], n)
                rest = buf[n * layout.size :]
            else:
                used = yield from self._unsorted(layouts, id_len, buf)
                rest = buf[used:]
        if rest:
            self.partial_records += 1

    def _unsorted(
        self, layouts: dict[int, RecordLayout], id_len: int, buf: bytes
    ) -> Generator[can.Message, None, int]:
        """Records of an unsorted data group (record id first); returns the bytes used."""
        id_fmt = {1: "<B", 2: "<H", 4: "<I", 8: "<Q"}.get(id_len)
        if id_fmt is None:
            return 0
        pos, end = 0, len(buf)
        # Consecutive records of one group are decoded together.
        run_layout: RecordLayout | None = None
        run: list[bytes] = []
        while pos + id_len <= end:
            (rid,) = struct.unpack_from(id_fmt, buf, pos)
            layout = layouts.get(rid)
            if layout is None:
                break  # an unknown record id: the records after it cannot be framed
            start = pos + id_len
            if layout.vlsd:
                if start + 4 > end:
                    break
                (n,) = struct.unpack_from("<I", buf, start)
                if start + 4 + n > end:
                    break
                pos = start + 4 + n
                continue
            if start + layout.size > end:
                break
            if layout is not run_layout and run:
                assert run_layout is not None
                yield from self._decode(run_layout, b"".join(run), len(run))
                run = []
            run_layout = layout
            if layout.kind is not None:
                run.append(buf[start : start + layout.size])
            pos = start + layout.size
        if run and run_layout is not None:
            yield from self._decode(run_layout, b"".join(run), len(run))
        return pos

    def _decode(self, layout: RecordLayout, data: bytes, n: int) -> Iterator[can.Message]:
        import numpy as np

        if n == 0 or layout.kind is None or layout.time is None:
            return
        rows = np.frombuffer(data, dtype=np.uint8).reshape(n, layout.size)
        times = _values(rows, layout.time)
        if layout.time_conversion is not None:
            times = layout.time_conversion.convert(times)
        times = np.asarray(times, dtype=np.float64) + self.start_timestamp
        cols = {name: _values(rows, fld) for name, fld in layout.fields.items()}
        checked = layout is PYTHON_CAN_LAYOUT
        kind = layout.kind
        for i in range(n):
            ts = float(times[i])
            if checked and not _plausible(cols, i, ts):
                return
            kv: dict[str, Any] = {"timestamp": ts}
            if "ID" in cols:
                kv["arbitration_id"] = int(cols["ID"][i]) & 0x1FFFFFFF
            if "BusChannel" in cols:
                kv["channel"] = int(cols["BusChannel"][i])
            if "Dir" in cols:
                kv["is_rx"] = int(cols["Dir"][i]) == 0
            if "IDE" in cols:
                kv["is_extended_id"] = bool(cols["IDE"][i])
            if kind == "remote":
                kv["is_remote_frame"] = True
                if "DLC" in cols:
                    kv["dlc"] = int(cols["DLC"][i])
            else:
                if kind == "error":
                    kv["is_error_frame"] = True
                for flag, key in (("EDL", "is_fd"), ("BRS", "bitrate_switch")):
                    if flag in cols:
                        kv[key] = bool(cols[flag][i])
                if "ESI" in cols:
                    kv["error_state_indicator"] = bool(cols["ESI"][i])
                if "DataBytes" in cols:
                    raw = cols["DataBytes"][i]
                    length = int(cols["DataLength"][i]) if "DataLength" in cols else len(raw)
                    kv["data"] = bytes(raw[:length])
            yield can.Message(**kv)

    # -- the account ---------------------------------------------------------------------

    def __enter__(self) -> Mf4Salvage:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def stop(self) -> None:
        """Nothing to close: the data was read while opening (python-can's reader API)."""
        self._groups = []

    def summary(self) -> str:
        """The one line said about the file after reading it."""
        if self.last_timestamp is None:
            upto = "(none before the cut)"
        else:
            when = datetime.fromtimestamp(self.last_timestamp, UTC)
            upto = "up to " + when.strftime("%Y-%m-%d %H:%M:%S.%f")[:-3] + " UTC"
        dropped = []
        if self.partial_records:
            dropped.append(f"{self.partial_records} partial record dropped")
        if self.lost_records:
            dropped.append(f"{self.lost_records} records of a compressed block cut short lost")
        extra = f" ({'; '.join(dropped)})" if dropped else ""
        return (
            f"truncated MF4: recovered {self.frames} frames {upto}, the rest of the file "
            f"is cut off{extra}"
        )


def _ts(msg: can.Message) -> float:
    return float(msg.timestamp)


def _peek_id(f: io.BufferedReader, address: int, size: int) -> bytes | None:
    head = _header(f, address, size)
    return None if head is None else head[0]


def _records_in(nbytes: int, layouts: dict[int, RecordLayout], id_len: int) -> int:
    if id_len == 0 and layouts:
        size = next(iter(layouts.values())).size
        return nbytes // size if size else 0
    return 0


def _values(rows: Any, fld: Field) -> Any:
    """One field of every record (rows: n x record size bytes) as a numpy array."""
    import numpy as np

    first = fld.byte_offset + fld.bit_offset // 8
    shift = fld.bit_offset % 8
    if fld.data_type == 10 or fld.bit_count > 64:  # a byte array
        return rows[:, first : first + fld.bit_count // 8]
    nbytes = (shift + fld.bit_count + 7) // 8
    raw = np.ascontiguousarray(rows[:, first : first + nbytes])
    if fld.data_type in (4, 5) and shift == 0 and fld.bit_count in (32, 64):  # IEEE floats
        order = "<" if fld.data_type == 4 else ">"
        return raw.view(f"{order}f{fld.bit_count // 8}").reshape(-1)
    if fld.data_type in (1, 3, 5):  # Motorola (big endian): as little endian bytes
        raw = raw[:, ::-1]
    value = np.zeros(len(rows), dtype=np.uint64)
    for k in range(nbytes):
        value |= raw[:, k].astype(np.uint64) << np.uint64(8 * k)
    value >>= np.uint64(shift)
    if fld.bit_count < 64:
        value &= np.uint64((1 << fld.bit_count) - 1)
    if fld.data_type in (2, 3) and fld.bit_count < 64:  # two's complement
        sign = np.uint64(1 << (fld.bit_count - 1))
        return (value ^ sign).astype(np.int64) - np.int64(1 << (fld.bit_count - 1))
    return value


def _plausible(cols: dict[str, Any], i: int, ts: float) -> bool:
    """A python-can MF4Writer record as that writer makes them."""
    if not math.isfinite(ts):
        return False
    for flag in ("IDE", "Dir", "EDL", "BRS", "ESI"):
        if int(cols[flag][i]) > 1:
            return False
    return int(cols["DataLength"][i]) <= 64 and int(cols["DLC"][i]) <= 15


def open_salvage(path: str | os.PathLike[str]) -> Mf4Salvage | None:
    """A salvage reader when the MF4 file at `path` is cut short; None when it is whole.
    Mf4SalvageError when it is cut short and nothing before the cut can be read."""
    cut = find_cut(path)
    if cut is None:
        return None
    return Mf4Salvage.open(path, cut)
