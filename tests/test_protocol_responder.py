"""The gateway's J1939-21 answers (pure): NACKs to requests, the receiving end of RTS/CTS
sessions with their timeouts and faults, and the passive RTS/CTS reassembly."""

from __future__ import annotations

from eqgw.protocol.responder import T2_S, GatewayResponder
from eqgw.protocol.transport import RtsCtsReassembler

GW = 0xD8
PAYLOAD = bytes(range(1, 21))  # 20 bytes: 3 packets


def rts(pgn: int, size: int = 20, packets: int = 3, per_cts: int = 0xFF) -> bytes:
    return bytes([0x10, size & 0xFF, size >> 8, packets, per_cts, pgn & 0xFF, pgn >> 8 & 0xFF, 0])


def dt(seq: int, data: bytes = PAYLOAD) -> bytes:
    return bytes([seq]) + data[(seq - 1) * 7 : seq * 7].ljust(7, b"\xff")


CM_TO_GW = 0x1CECD81E  # TP.CM from 0x1E to 0xD8
DT_TO_GW = 0x1CEBD81E


def test_requests_to_the_gateway_are_nacked_and_others_are_not() -> None:
    r = GatewayResponder(GW)
    assert r.on_frame(0x18EAD880, b"\xeb\xfe\x00", 0.0) == [
        (0x18E8FFD8, bytes([1, 0xFF, 0xFF, 0xFF, 0x80, 0xEB, 0xFE, 0]))
    ]
    assert r.on_frame(0x18EAFF80, b"\xeb\xfe\x00", 0.0) == []  # to all
    assert r.on_frame(0x18EA1E80, b"\xeb\xfe\x00", 0.0) == []  # to another node
    assert r.on_frame(0x18EAD880, b"\x00\xee\x00", 0.0) == []  # the claim answers that
    assert r.on_frame(0x18EAD880, b"\xeb", 0.0) == []  # too short to name a PGN
    assert r.stats.nacks == 1


def test_a_taken_transfer_gets_a_cts_per_window_and_an_eoma() -> None:
    r = GatewayResponder(GW)
    (cts,) = r.on_frame(CM_TO_GW, rts(0xFECA, per_cts=2), 0.0)
    assert cts == (0x1CEC1ED8, bytes([0x11, 2, 1, 0xFF, 0xFF, 0xCA, 0xFE, 0]))
    assert r.on_frame(DT_TO_GW, dt(1), 0.1) == []
    (cts2,) = r.on_frame(DT_TO_GW, dt(2), 0.2)
    assert cts2[1][:3] == bytes([0x11, 1, 3])
    (eoma,) = r.on_frame(DT_TO_GW, dt(3), 0.3)
    assert eoma[1] == bytes([0x13, 20, 0, 3, 0xFF, 0xCA, 0xFE, 0])
    assert r.pending() == 0 and r.stats.sessions_completed == 1


def test_refusals_timeouts_and_bad_sequences_are_aborted() -> None:
    r = GatewayResponder(GW)
    (abort,) = r.on_frame(CM_TO_GW, rts(0xEF00), 0.0)  # a PGN it does not take
    assert abort[1][:2] == bytes([0xFF, 250])
    (abort,) = r.on_frame(CM_TO_GW, rts(0xFECA, size=2000, packets=0), 0.0)
    assert abort[1][:2] == bytes([0xFF, 9])  # larger than 1785 bytes
    r.on_frame(CM_TO_GW, rts(0xFECA), 0.0)
    (busy,) = r.on_frame(CM_TO_GW, rts(0xFEEB), 0.0)  # another PGN while one is open
    assert busy[1][:2] == bytes([0xFF, 1]) and r.pending() == 1
    (bad,) = r.on_frame(DT_TO_GW, dt(2), 0.1)
    assert bad[1][:2] == bytes([0xFF, 7]) and r.pending() == 0
    r.on_frame(CM_TO_GW, rts(0xFECA), 1.0)
    assert r.expire(1.0 + T2_S - 0.01) == []
    (late,) = r.expire(1.0 + T2_S + 0.01)
    assert late[1][:2] == bytes([0xFF, 3]) and r.pending() == 0
    # The sender's own abort ends the session quietly.
    r.on_frame(CM_TO_GW, rts(0xFECA), 5.0)
    assert r.on_frame(CM_TO_GW, bytes([0xFF, 1, 0xFF, 0xFF, 0xFF, 0xCA, 0xFE, 0]), 5.1) == []
    assert r.pending() == 0


def test_passive_reassembly_takes_retransmissions_and_drops_aborted_sessions() -> None:
    p = RtsCtsReassembler()
    assert p.feed(0.0, "c", 0x1E, GW, 0xEC00, rts(0xFECA)) is None
    assert p.feed(0.1, "c", 0x1E, GW, 0xEB00, dt(1, b"x" * 20)) is None  # a bad copy...
    assert p.feed(0.2, "c", 0x1E, GW, 0xEB00, dt(1)) is None  # ...sent again on a new CTS
    assert p.feed(0.3, "c", 0x1E, GW, 0xEB00, dt(2)) is None
    done = p.feed(0.4, "c", 0x1E, GW, 0xEB00, dt(3))
    assert done is not None and done.payload == PAYLOAD and done.pgn == 0xFECA
    p.feed(1.0, "c", 0x1E, GW, 0xEC00, rts(0xFECA))
    p.feed(1.1, "c", 0x1E, GW, 0xEC00, bytes([0xFF, 3, 0xFF, 0xFF, 0xFF, 0xCA, 0xFE, 0]))
    assert p.feed(1.2, "c", 0x1E, GW, 0xEB00, dt(1)) is None and p.pending() == 0
    assert (p.stats.completed, p.stats.incomplete) == (1, 1)
