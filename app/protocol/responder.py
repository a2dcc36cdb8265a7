"""The gateway's answers to other nodes (J1939-21), as pure state: no I/O.

A bus's transmit path (eqgw.bus.reader) feeds `GatewayResponder.on_frame` every request and
transport-protocol frame addressed to the gateway, calls `expire` now and then, and sends what
they return (only while the gateway holds its address):

- A request sent to the gateway's address for a PGN it does not serve is answered with a NACK
  (Acknowledgement PGN 59392, to all, naming the requester and the PGN). The gateway serves no
  PGN on request except its address claim (PGN 60928, answered by `AddressClaimer`). Requests
  sent to all are not answered (J1939-21: no NACK to a global request).
- An RTS (TP.CM, connection mode) addressed to the gateway is answered: for a PGN the gateway
  takes (DM1, component ID, software ID: what it decodes) with CTS frames as the data arrives
  and an End of Message Acknowledgement when it is complete; for anything else with a
  Connection Abort. The data itself is reassembled by the decoder like any other node's
  (`transport.RtsCtsReassembler`), so the gateway's own transfers and other nodes' are decoded
  alike.
"""

from __future__ import annotations

from dataclasses import dataclass

from eqgw.protocol.acknowledgement import encode_acknowledgement
from eqgw.protocol.j1939 import (
    PGN_COMPONENT_ID,
    PGN_DM1,
    PGN_REQUEST,
    PGN_SOFTWARE_ID,
    PGN_TP_CM,
    PGN_TP_DT,
    PRIORITY_TP_DT,
    compose_id,
)
from eqgw.protocol.transport import (
    BAM_MAX_SIZE,
    BAM_MIN_SIZE,
    BYTES_PER_PACKET,
    CONTROL_ABORT,
    CONTROL_CTS,
    CONTROL_EOMA,
    CONTROL_RTS,
)

Frame = tuple[int, bytes]

PGN_ADDRESS_CLAIMED = 0xEE00  # answered by AddressClaimer, not here
# The PGNs the gateway takes by RTS/CTS: those it decodes from an equalizer.
TAKEN_PGNS = frozenset({PGN_DM1, PGN_COMPONENT_ID, PGN_SOFTWARE_ID})
# J1939-21 timeouts: T1 between data packets, T2 from a CTS to the first packet it allows.
T1_S = 0.75
T2_S = 1.25
# J1939-21 Connection Abort reasons.
ABORT_BUSY = 1  # already in a session with that node for another PGN
ABORT_TIMEOUT = 3
ABORT_BAD_SEQUENCE = 7
ABORT_TOO_LARGE = 9
ABORT_OTHER = 250  # "any other reason": here, a PGN the gateway does not take


@dataclass(slots=True)
class _Session:
    pgn: int
    size: int
    packets: int
    per_cts: int  # packets the sender may send per CTS (RTS byte 5; 0xFF: no limit)
    next_seq: int  # the next packet expected
    window_end: int  # the last packet the latest CTS allowed
    deadline: float  # the sender must have sent a packet by then


@dataclass(slots=True)
class ResponderStats:
    """What the gateway answered."""

    nacks: int = 0
    sessions_accepted: int = 0
    sessions_completed: int = 0
    sessions_aborted: int = 0
    # Answers decided while the gateway could not transmit (no address, fenced): not sent.
    withheld: int = 0


def _pgn_at(data: bytes, offset: int) -> int:
    return data[offset] | (data[offset + 1] << 8) | (data[offset + 2] << 16)


def _cm(control: int, a: int, b: int, c: int, d: int, pgn: int) -> bytes:
    return bytes((control, a, b, c, d, pgn & 0xFF, (pgn >> 8) & 0xFF, (pgn >> 16) & 0xFF))


class GatewayResponder:
    """Answers the requests and RTS/CTS sessions other nodes address to the gateway."""

    def __init__(self, address: int, taken: frozenset[int] = TAKEN_PGNS) -> None:
        self.address = address
        self.taken = taken
        self.stats = ResponderStats()
        self._sessions: dict[int, _Session] = {}  # by sender's address

    def on_frame(self, can_id: int, data: bytes, now: float) -> list[Frame]:
        """A frame received on the bus; returns the frames to send in answer (maybe none)."""
        pf = (can_id >> 16) & 0xFF
        da = (can_id >> 8) & 0xFF
        sa = can_id & 0xFF
        if pf >= 240 or da != self.address or sa == self.address:
            return []
        if pf == PGN_REQUEST >> 8:
            return self._request(sa, data)
        if pf == PGN_TP_CM >> 8:
            return self._connection_management(sa, data, now)
        if pf == PGN_TP_DT >> 8:
            return self._data(sa, data, now)
        return []

    def expire(self, now: float) -> list[Frame]:
        """Abort sessions whose sender stopped (J1939-21 T1/T2): the frames to send."""
        out: list[Frame] = []
        for sa, s in list(self._sessions.items()):
            if now > s.deadline:
                out.append(self._abort(sa, ABORT_TIMEOUT, s.pgn))
        return out

    def pending(self) -> int:
        """Sessions open with other nodes."""
        return len(self._sessions)

    # -- requests ----------------------------------------------------------------------------

    def _request(self, sa: int, data: bytes) -> list[Frame]:
        if len(data) < 3:
            return []
        pgn = _pgn_at(data, 0)
        if pgn == PGN_ADDRESS_CLAIMED:
            return []  # the address claim answers it
        self.stats.nacks += 1
        return [encode_acknowledgement("nack", pgn, sa=self.address, address=sa)]

    # -- connection-mode transfers ----------------------------------------------------------

    def _tp_cm_id(self, to: int) -> int:
        return compose_id(PGN_TP_CM, self.address, to, PRIORITY_TP_DT)

    def _abort(self, sa: int, reason: int, pgn: int) -> Frame:
        self._sessions.pop(sa, None)
        self.stats.sessions_aborted += 1
        return (self._tp_cm_id(sa), _cm(CONTROL_ABORT, reason, 0xFF, 0xFF, 0xFF, pgn))

    def _cts(self, sa: int, s: _Session, now: float) -> Frame:
        count = s.packets - s.next_seq + 1
        if s.per_cts != 0xFF:
            count = min(count, max(1, s.per_cts))
        s.window_end = s.next_seq + count - 1
        s.deadline = now + T2_S
        return (self._tp_cm_id(sa), _cm(CONTROL_CTS, count, s.next_seq, 0xFF, 0xFF, s.pgn))

    def _connection_management(self, sa: int, data: bytes, now: float) -> list[Frame]:
        if len(data) < 8:
            return []
        control = data[0]
        pgn = _pgn_at(data, 5)
        if control == CONTROL_ABORT:
            session = self._sessions.get(sa)
            if session is not None and session.pgn == pgn:
                del self._sessions[sa]
                self.stats.sessions_aborted += 1
            return []
        if control != CONTROL_RTS:
            return []  # CTS/EoMA to us: the gateway sends nothing by RTS/CTS
        size = data[1] | (data[2] << 8)
        packets = data[3]
        current = self._sessions.get(sa)
        if current is not None and current.pgn != pgn:
            # J1939-21: one session at a time between two nodes; the new one is refused.
            return [(self._tp_cm_id(sa), _cm(CONTROL_ABORT, ABORT_BUSY, 0xFF, 0xFF, 0xFF, pgn))]
        if size > BAM_MAX_SIZE:
            return [self._abort(sa, ABORT_TOO_LARGE, pgn)]
        if pgn not in self.taken or size < BAM_MIN_SIZE or packets != -(-size // BYTES_PER_PACKET):
            return [self._abort(sa, ABORT_OTHER, pgn)]
        # A repeated RTS for the same PGN starts the transfer over.
        session = _Session(pgn, size, packets, data[4], 1, 0, now)
        self._sessions[sa] = session
        self.stats.sessions_accepted += 1
        return [self._cts(sa, session, now)]

    def _data(self, sa: int, data: bytes, now: float) -> list[Frame]:
        s = self._sessions.get(sa)
        if s is None or not data:
            return []
        seq = data[0]
        if seq != s.next_seq or seq > s.window_end:
            return [self._abort(sa, ABORT_BAD_SEQUENCE, s.pgn)]
        s.next_seq += 1
        s.deadline = now + T1_S
        if seq == s.packets:
            del self._sessions[sa]
            self.stats.sessions_completed += 1
            eoma = _cm(CONTROL_EOMA, s.size & 0xFF, s.size >> 8, s.packets, 0xFF, s.pgn)
            return [(self._tp_cm_id(sa), eoma)]
        if seq == s.window_end:
            return [self._cts(sa, s, now)]
        return []
