"""J1939-21 transport protocol: passive BAM and RTS/CTS reassembly, BAM frame encoding."""

from __future__ import annotations

from dataclasses import dataclass

from eqgw.protocol.errors import EncodeError
from eqgw.protocol.j1939 import (
    GLOBAL_ADDRESS,
    PGN_TP_CM,
    PGN_TP_DT,
    PRIORITY_DEFAULT,
    PRIORITY_TP_DT,
    compose_id,
)

CONTROL_RTS = 0x10
CONTROL_CTS = 0x11
CONTROL_EOMA = 0x13
CONTROL_BAM = 0x20
CONTROL_ABORT = 0xFF
# RTS/CTS: a session with no packet for this long is over (J1939-21 T2 is 1.25 s from a CTS).
RTS_IDLE_S = 1.25
BAM_MIN_SIZE = 9
BAM_MAX_SIZE = 1785
BYTES_PER_PACKET = 7
T1_SECONDS = 0.75

_Key = tuple[str | None, int]


@dataclass(frozen=True, slots=True)
class Transfer:
    """A reassembled BAM payload; `ts` is the timestamp of its last packet."""

    ts: float
    channel: str | None
    sa: int
    pgn: int
    payload: bytes


@dataclass(slots=True)
class TransportStats:
    """Counters of what the reassembler saw, for bus health reporting."""

    completed: int = 0
    # Announced transfers that stopped: timed out, superseded by a new BAM, or aborted.
    incomplete: int = 0
    # Protocol faults: malformed TP.CM, short TP.DT, a sequence error, or an orphan TP.DT.
    broken: int = 0
    # TP.DT packets with no announcement to belong to (also counted in `broken`).
    orphan_packets: int = 0


@dataclass(slots=True)
class _Session:
    pgn: int
    size: int
    packets: int
    next_seq: int
    last_ts: float
    data: bytearray


def _packet_count(size: int) -> int:
    return -(-size // BYTES_PER_PACKET)


class BamReassembler:
    """Rebuilds BAM transfers from TP.CM/TP.DT frames, one open transfer per (channel, SA)."""

    def __init__(self, t1: float = T1_SECONDS) -> None:
        self.t1 = t1
        self.stats = TransportStats()
        self._sessions: dict[_Key, _Session] = {}
        # Keys whose transfer was dropped, with the time of its latest packet or of the drop:
        # the rest of that transfer is discarded quietly instead of each packet being an orphan.
        self._discarding: dict[_Key, float] = {}

    def pending(self) -> int:
        """Number of transfers announced and not yet finished."""
        return len(self._sessions)

    def expire(self, now: float) -> int:
        """Drop transfers idle for more than t1 at `now`; returns how many were dropped."""
        for key in [k for k, ts in self._discarding.items() if now - ts > self.t1]:
            del self._discarding[key]
        stale = [key for key, s in self._sessions.items() if now - s.last_ts > self.t1]
        for key in stale:
            self._drop(key, now, broken=False)
        return len(stale)

    def feed(
        self, ts: float, channel: str | None, sa: int, da: int, pgn: int, data: bytes
    ) -> Transfer | None:
        """Take one TP.CM/TP.DT frame (others are ignored); returns the Transfer it completes."""
        key = (channel, sa)
        session = self._sessions.get(key)
        if session is not None and ts - session.last_ts > self.t1:
            self._drop(key, ts, broken=False)
            session = None
        if pgn == PGN_TP_CM:
            self._connection_management(ts, key, da, data, session)
            return None
        if pgn == PGN_TP_DT:
            return self._data_transfer(ts, key, da, data, session)
        return None

    def _drop(self, key: _Key, ts: float, *, broken: bool) -> None:
        # `ts` is when the loss was noticed: late packets of the lost transfer that follow
        # within t1 are its tail, not orphans.
        del self._sessions[key]
        self._discarding[key] = ts
        if broken:
            self.stats.broken += 1
        else:
            self.stats.incomplete += 1

    def _connection_management(
        self, ts: float, key: _Key, da: int, data: bytes, session: _Session | None
    ) -> None:
        if not data:
            self.stats.broken += 1
            return
        control = data[0]
        if control == CONTROL_ABORT:
            if len(data) < 8:
                self.stats.broken += 1
            elif session is not None and _pgn_at(data, 5) == session.pgn:
                self._drop(key, ts, broken=False)
            return
        if control != CONTROL_BAM:
            # RTS/CTS/EoMA belong to connection-mode transfers to one node; not ours to follow.
            return
        if session is not None:
            self._drop(key, ts, broken=False)
        if len(data) < 8 or da != GLOBAL_ADDRESS:
            self._discarding[key] = ts
            self.stats.broken += 1
            return
        size = data[1] | (data[2] << 8)
        packets = data[3]
        announced_pgn = _pgn_at(data, 5)
        if (
            not BAM_MIN_SIZE <= size <= BAM_MAX_SIZE
            or packets != _packet_count(size)
            or announced_pgn > 0x3FFFF
        ):
            self._discarding[key] = ts
            self.stats.broken += 1
            return
        self._discarding.pop(key, None)
        self._sessions[key] = _Session(
            pgn=announced_pgn,
            size=size,
            packets=packets,
            next_seq=1,
            last_ts=ts,
            data=bytearray(),
        )

    def _data_transfer(
        self, ts: float, key: _Key, da: int, data: bytes, session: _Session | None
    ) -> Transfer | None:
        if da != GLOBAL_ADDRESS:
            # Data of an RTS/CTS connection to one node; a BAM's packets are always global.
            return None
        if session is None:
            discarded_at = self._discarding.get(key)
            if discarded_at is not None and ts - discarded_at <= self.t1:
                self._discarding[key] = ts
                return None
            self._discarding.pop(key, None)
            self.stats.orphan_packets += 1
            self.stats.broken += 1
            return None
        seq = data[0] if data else -1
        needed = min(BYTES_PER_PACKET, session.size - len(session.data))
        if seq != session.next_seq or len(data) < 1 + needed:
            # BAM has no retransmission: any gap, repeat or reordering loses the transfer.
            self._drop(key, ts, broken=True)
            return None
        session.data += data[1 : 1 + needed]
        session.last_ts = ts
        if seq < session.packets:
            session.next_seq += 1
            return None
        del self._sessions[key]
        self.stats.completed += 1
        channel, sa = key
        return Transfer(ts, channel, sa, session.pgn, bytes(session.data))


@dataclass(slots=True)
class _RtsSession:
    pgn: int
    size: int
    packets: int
    last_ts: float
    chunks: dict[int, bytes]


class RtsCtsReassembler:
    """Rebuilds connection-mode (RTS/CTS) transfers from the sender's TP.CM RTS and TP.DT
    frames, passively, one open transfer per (channel, sender, receiver). A packet sent again
    (the receiver asked for it again with a CTS) replaces the earlier copy; the transfer is
    complete when every packet is in. An abort, a new RTS or `RTS_IDLE_S` of silence ends an
    open transfer incomplete. Stats count like BamReassembler's."""

    def __init__(self, idle: float = RTS_IDLE_S) -> None:
        self.idle = idle
        self.stats = TransportStats()
        self._sessions: dict[tuple[str | None, int, int], _RtsSession] = {}

    def pending(self) -> int:
        return len(self._sessions)

    def expire(self, now: float) -> int:
        stale = [k for k, s in self._sessions.items() if now - s.last_ts > self.idle]
        for key in stale:
            del self._sessions[key]
            self.stats.incomplete += 1
        return len(stale)

    def feed(
        self, ts: float, channel: str | None, sa: int, da: int, pgn: int, data: bytes
    ) -> Transfer | None:
        """One TP.CM/TP.DT frame from `sa` to `da` (not global); the Transfer it completes."""
        key = (channel, sa, da)
        session = self._sessions.get(key)
        if session is not None and ts - session.last_ts > self.idle:
            del self._sessions[key]
            self.stats.incomplete += 1
            session = None
        if pgn == PGN_TP_CM:
            if len(data) < 8:
                self.stats.broken += 1
                return None
            control = data[0]
            if control == CONTROL_ABORT:
                if session is not None:
                    del self._sessions[key]
                    self.stats.incomplete += 1
                return None
            if control != CONTROL_RTS:
                return None
            if session is not None:
                self.stats.incomplete += 1
            size = data[1] | (data[2] << 8)
            packets = data[3]
            if not BAM_MIN_SIZE <= size <= BAM_MAX_SIZE or packets != _packet_count(size):
                self._sessions.pop(key, None)
                self.stats.broken += 1
                return None
            self._sessions[key] = _RtsSession(_pgn_at(data, 5), size, packets, ts, {})
            return None
        if pgn != PGN_TP_DT or session is None or not data:
            return None
        seq = data[0]
        if not 1 <= seq <= session.packets:
            del self._sessions[key]
            self.stats.broken += 1
            return None
        needed = min(BYTES_PER_PACKET, session.size - (seq - 1) * BYTES_PER_PACKET)
        if len(data) < 1 + needed:
            del self._sessions[key]
            self.stats.broken += 1
            return None
        session.chunks[seq] = bytes(data[1 : 1 + needed])
        session.last_ts = ts
        if len(session.chunks) < session.packets:
            return None
        del self._sessions[key]
        self.stats.completed += 1
        payload = b"".join(session.chunks[i] for i in range(1, session.packets + 1))
        return Transfer(ts, channel, sa, session.pgn, payload)


def is_rts(data: bytes) -> bool:
    """Whether a TP.CM frame's payload is a Request To Send."""
    return len(data) >= 8 and data[0] == CONTROL_RTS


def announced_pgn(data: bytes) -> int:
    """The PGN a TP.CM frame names (bytes 6-8)."""
    return _pgn_at(data, 5)


def _pgn_at(data: bytes, offset: int) -> int:
    return data[offset] | (data[offset + 1] << 8) | (data[offset + 2] << 16)


def encode_bam(
    pgn: int, payload: bytes, *, sa: int, priority: int = PRIORITY_DEFAULT
) -> list[tuple[int, bytes]]:
    """Frames of a BAM broadcast of `payload`: the TP.CM announcement, then the TP.DT packets."""
    size = len(payload)
    if not BAM_MIN_SIZE <= size <= BAM_MAX_SIZE:
        raise EncodeError(f"BAM payload must be {BAM_MIN_SIZE}..{BAM_MAX_SIZE} bytes, got {size}")
    if not 0 <= pgn <= 0x3FFFF:
        raise EncodeError(f"PGN {pgn} out of range")
    try:
        cm_id = compose_id(PGN_TP_CM, sa, GLOBAL_ADDRESS, priority)
        # Data packets go at priority 7 whatever the announcement's (J1939-21, and the manuals).
        dt_id = compose_id(PGN_TP_DT, sa, GLOBAL_ADDRESS, PRIORITY_TP_DT)
    except ValueError as exc:
        raise EncodeError(str(exc)) from exc
    packets = _packet_count(size)
    announce = bytes(
        (
            CONTROL_BAM,
            size & 0xFF,
            size >> 8,
            packets,
            0xFF,
            pgn & 0xFF,
            (pgn >> 8) & 0xFF,
            pgn >> 16,
        )
    )
    frames = [(cm_id, announce)]
    for seq in range(1, packets + 1):
        chunk = bytes(payload[(seq - 1) * BYTES_PER_PACKET : seq * BYTES_PER_PACKET])
        frames.append((dt_id, bytes((seq,)) + chunk.ljust(BYTES_PER_PACKET, b"\xff")))
    return frames
