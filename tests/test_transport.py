"""BAM transport: the manuals' DM1 frame layout, the reassembler's rules, and stream properties."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from eqgw.protocol.dm1 import encode_dm1
from eqgw.protocol.errors import EncodeError
from eqgw.protocol.j1939 import PGN_DM1, PGN_TP_CM, PGN_TP_DT, compose_id, parse_id
from eqgw.protocol.transport import BamReassembler, Transfer, TransportStats, encode_bam

SA = 0x1E
CM_ID = 0x18ECFF1E  # the manuals' TP.CM identifier
DT_ID = 0x1CEBFF1E  # priority 7, although the manuals' table prints 0x18EBFF1E

OVF = {"spn": 168, "fmi": 0, "oc": 1}
IMB = {"spn": 520448, "fmi": 0, "oc": 2}
EQFLT = {"spn": 520449, "fmi": 1, "oc": 3}
UVF = {"spn": 168, "fmi": 1, "oc": 4}
OTHER = {"spn": 0x51234, "fmi": 5, "oc": 6}
AWL = {"awl": 2}


def frames_hex(frames: Sequence[tuple[int, bytes]]) -> list[tuple[int, str]]:
    return [(can_id, data.hex(" ").upper()) for can_id, data in frames]


def feed(
    reassembler: BamReassembler, ts: float, can_id: int, data: bytes, channel: str | None = "can0"
) -> Transfer | None:
    j = parse_id(can_id)
    return reassembler.feed(ts, channel, j.sa, j.da, j.pgn, data)


def feed_all(
    reassembler: BamReassembler,
    frames: Sequence[tuple[int, bytes]],
    *,
    t0: float = 0.0,
    step: float = 0.05,
    channel: str | None = "can0",
) -> list[Transfer]:
    results = [feed(reassembler, t0 + i * step, f[0], f[1], channel) for i, f in enumerate(frames)]
    return [r for r in results if r is not None]


def stats(
    completed: int = 0, incomplete: int = 0, broken: int = 0, orphan_packets: int = 0
) -> TransportStats:
    return TransportStats(completed, incomplete, broken, orphan_packets)


# --- the manuals' BAM layout of a multi-DTC DM1 -------------------------------------------


@pytest.mark.parametrize(
    ("dtcs", "expected"),
    [
        pytest.param(
            [OVF, IMB],
            [
                (CM_ID, "20 0A 00 02 FF CA FE 00"),
                (DT_ID, "01 08 00 A8 00 00 01 00"),
                # Byte 4 is DTC2's CM/OC (the manuals say DTC1's, SPEC-NOTES errata).
                (DT_ID, "02 F1 E0 02 FF FF FF FF"),
            ],
            id="2-dtcs",
        ),
        pytest.param(
            [OVF, IMB, EQFLT],
            [
                (CM_ID, "20 0E 00 02 FF CA FE 00"),
                (DT_ID, "01 08 00 A8 00 00 01 00"),
                (DT_ID, "02 F1 E0 02 01 F1 E1 03"),
            ],
            id="3-dtcs",
        ),
        pytest.param(
            [OVF, IMB, EQFLT, UVF, OTHER],
            [
                (CM_ID, "20 16 00 04 FF CA FE 00"),
                (DT_ID, "01 08 00 A8 00 00 01 00"),
                (DT_ID, "02 F1 E0 02 01 F1 E1 03"),
                (DT_ID, "03 A8 00 01 04 34 12 A5"),
                # The manuals stop at the third packet; DTC5's CM/OC needs a fourth.
                (DT_ID, "04 06 FF FF FF FF FF FF"),
            ],
            id="5-dtcs",
        ),
    ],
)
def test_manual_bam_layout(dtcs: list[dict[str, int]], expected: list[tuple[int, str]]) -> None:
    payload = encode_dm1(AWL, dtcs)
    frames = encode_bam(PGN_DM1, payload, sa=SA)
    assert frames_hex(frames) == expected
    assert all(len(data) == 8 for _, data in frames)
    # The same PGN and SA as the manuals' 0x18EBFF1E, only the priority differs.
    assert (parse_id(DT_ID).pgn, parse_id(DT_ID).sa) == (PGN_TP_DT, SA)
    assert (parse_id(0x18EBFF1E).pgn, parse_id(0x18EBFF1E).sa) == (PGN_TP_DT, SA)
    transfers = feed_all(BamReassembler(), frames)
    assert transfers == [Transfer(0.05 * (len(frames) - 1), "can0", SA, PGN_DM1, payload)]


def test_encode_bam_ids_and_priority() -> None:
    frames = encode_bam(0x1FF00, bytes(range(9)), sa=0x41, priority=3)
    assert frames_hex(frames) == [
        (compose_id(PGN_TP_CM, 0x41, 0xFF, 3), "20 09 00 02 FF 00 FF 01"),
        (compose_id(PGN_TP_DT, 0x41, 0xFF, 7), "01 00 01 02 03 04 05 06"),
        (compose_id(PGN_TP_DT, 0x41, 0xFF, 7), "02 07 08 FF FF FF FF FF"),
    ]
    assert frames[0][0] == 0x0CECFF41 and frames[1][0] == 0x1CEBFF41


def test_encode_bam_largest() -> None:
    payload = bytes(i % 251 for i in range(1785))
    frames = encode_bam(PGN_DM1, payload, sa=SA)
    assert len(frames) == 256
    assert frames[0][1] == bytes.fromhex("20 F9 06 FF FF CA FE 00")
    assert frames[-1][1] == bytes((255,)) + payload[-7:]
    assert feed_all(BamReassembler(), frames, step=0.001)[0].payload == payload


@pytest.mark.parametrize(
    ("pgn", "size", "sa", "priority"),
    [
        pytest.param(PGN_DM1, 8, SA, 6, id="too-short"),
        pytest.param(PGN_DM1, 1786, SA, 6, id="too-long"),
        pytest.param(0x40000, 9, SA, 6, id="pgn-too-big"),
        pytest.param(-1, 9, SA, 6, id="pgn-negative"),
        pytest.param(PGN_DM1, 9, 256, 6, id="sa-too-big"),
        pytest.param(PGN_DM1, 9, SA, 8, id="priority-too-big"),
    ],
)
def test_encode_bam_rejects(pgn: int, size: int, sa: int, priority: int) -> None:
    with pytest.raises(EncodeError):
        encode_bam(pgn, bytes(size), sa=sa, priority=priority)


# --- reassembly rules ---------------------------------------------------------------------

PAYLOAD = bytes(range(1, 20))  # 19 bytes: 3 packets, the last one with 2 bytes of padding
FRAMES = encode_bam(PGN_DM1, PAYLOAD, sa=SA)
CM, DT1, DT2, DT3 = (data for _, data in FRAMES)


def test_completes_with_timestamp_of_last_packet_and_truncated_payload() -> None:
    r = BamReassembler()
    assert feed(r, 10.0, CM_ID, CM) is None
    assert r.pending() == 1
    assert feed(r, 10.1, DT_ID, DT1) is None
    assert feed(r, 10.2, DT_ID, DT2) is None
    assert feed(r, 10.3, DT_ID, DT3) == Transfer(10.3, "can0", SA, PGN_DM1, PAYLOAD)
    assert r.pending() == 0
    assert r.stats == stats(completed=1)


def test_keys_are_channel_and_sa() -> None:
    r = BamReassembler()
    other_sa = encode_bam(PGN_DM1, bytes(10), sa=0x1F)
    out = [
        feed(r, 0.0, CM_ID, CM, "can0"),
        feed(r, 0.0, CM_ID, CM, "can1"),
        feed(r, 0.0, *other_sa[0]),
        feed(r, 0.0, CM_ID, CM, None),
        feed(r, 0.1, DT_ID, DT1, "can1"),
        feed(r, 0.1, DT_ID, DT1, "can0"),
        feed(r, 0.1, *other_sa[1]),
        feed(r, 0.2, DT_ID, DT2, "can0"),
        feed(r, 0.2, *other_sa[2]),
        feed(r, 0.2, DT_ID, DT2, "can1"),
        feed(r, 0.3, DT_ID, DT3, "can1"),
        feed(r, 0.3, DT_ID, DT3, "can0"),
    ]
    assert [t for t in out if t is not None] == [
        Transfer(0.2, "can0", 0x1F, PGN_DM1, bytes(10)),
        Transfer(0.3, "can1", SA, PGN_DM1, PAYLOAD),
        Transfer(0.3, "can0", SA, PGN_DM1, PAYLOAD),
    ]
    assert r.pending() == 1  # channel None never got its data
    assert r.stats == stats(completed=3)


def test_new_announcement_replaces_the_open_transfer() -> None:
    r = BamReassembler()
    other = encode_bam(0xFEEB, b"*EQ8001*rev", sa=SA)
    assert feed_all(r, [FRAMES[0], FRAMES[1], *other]) == [
        Transfer(0.2, "can0", SA, 0xFEEB, b"*EQ8001*rev")
    ]
    assert r.stats == stats(completed=1, incomplete=1)


def test_repeated_announcement_restarts() -> None:
    r = BamReassembler()
    assert feed_all(r, [FRAMES[0], FRAMES[1], *FRAMES])[0].payload == PAYLOAD
    assert r.stats == stats(completed=1, incomplete=1)


def _abort(pgn: int) -> bytes:
    return bytes((0xFF, 0x03, 0xFF, 0xFF, 0xFF, pgn & 0xFF, (pgn >> 8) & 0xFF, pgn >> 16))


def test_abort_of_the_announced_pgn_drops_the_transfer() -> None:
    r = BamReassembler()
    frames = [FRAMES[0], FRAMES[1], (CM_ID, _abort(PGN_DM1)), FRAMES[2], FRAMES[3]]
    assert feed_all(r, frames) == []
    # The rest of the aborted transfer is its tail, not orphans.
    assert r.stats == stats(incomplete=1)
    assert r.pending() == 0


def test_abort_of_another_pgn_is_not_ours() -> None:
    r = BamReassembler()
    abort_other = (compose_id(PGN_TP_CM, SA, 0x41), _abort(0xFEDA))
    assert feed_all(r, [FRAMES[0], FRAMES[1], abort_other, FRAMES[2], FRAMES[3]])[0].payload == (
        PAYLOAD
    )
    assert r.stats == stats(completed=1)


@pytest.mark.parametrize(
    "control", [pytest.param(c, id=f"{c:#04x}") for c in (0x10, 0x11, 0x13, 0x00, 0x21)]
)
def test_other_control_bytes_are_ignored(control: int) -> None:
    r = BamReassembler()
    rts_cts = (compose_id(PGN_TP_CM, SA, 0x41), bytes((control, 20, 0, 3, 1, 0xCA, 0xFE, 0)))
    # Connection-mode data to one node from the same SA does not disturb the broadcast either.
    rts_data = (compose_id(PGN_TP_DT, SA, 0x41, 7), bytes((1, 9, 9, 9, 9, 9, 9, 9)))
    frames = [FRAMES[0], rts_cts, FRAMES[1], rts_data, FRAMES[2], FRAMES[3]]
    assert feed_all(r, frames)[0].payload == PAYLOAD
    assert r.stats == stats(completed=1)


def test_non_transport_pgn_is_ignored() -> None:
    r = BamReassembler()
    assert r.feed(0.0, "can0", SA, 0xFF, PGN_DM1, bytes(8)) is None
    assert r.stats == stats() and r.pending() == 0


@pytest.mark.parametrize(
    ("da", "cm"),
    [
        pytest.param(0xFF, "20 13 00 03 FF CA FE", id="short-cm"),
        pytest.param(0xFF, "20 08 00 02 FF CA FE 00", id="size-8"),
        pytest.param(0xFF, "20 FA 06 FF FF CA FE 00", id="size-1786"),
        pytest.param(0xFF, "20 13 00 04 FF CA FE 00", id="packet-count-too-big"),
        pytest.param(0xFF, "20 13 00 02 FF CA FE 00", id="packet-count-too-small"),
        pytest.param(0xFF, "20 13 00 03 FF CA FE 04", id="pgn-too-big"),
        pytest.param(0x41, "20 13 00 03 FF CA FE 00", id="bam-to-one-node"),
    ],
)
def test_malformed_announcement_is_broken(da: int, cm: str) -> None:
    r = BamReassembler()
    can_id = compose_id(PGN_TP_CM, SA, da)
    assert feed_all(r, [(can_id, bytes.fromhex(cm)), *FRAMES[1:]]) == []
    # Its data packets are dropped with it, not counted again as orphans.
    assert r.stats == stats(broken=1)
    assert r.pending() == 0


def test_empty_announcement_is_broken() -> None:
    # With no control byte there is no telling what it was, so the packets after it are orphans.
    r = BamReassembler()
    assert feed_all(r, [(CM_ID, b""), *FRAMES[1:]]) == []
    assert r.stats == stats(broken=4, orphan_packets=3)


def test_short_abort_is_broken_and_keeps_the_transfer() -> None:
    r = BamReassembler()
    frames = [FRAMES[0], FRAMES[1], (CM_ID, b"\xff\x03"), FRAMES[2], FRAMES[3]]
    assert feed_all(r, frames)[0].payload == PAYLOAD
    assert r.stats == stats(completed=1, broken=1)


def test_malformed_announcement_drops_the_open_transfer() -> None:
    r = BamReassembler()
    frames = [FRAMES[0], FRAMES[1], (CM_ID, bytes.fromhex("20 08 00 02 FF CA FE 00")), *FRAMES[2:]]
    assert feed_all(r, frames) == []
    assert r.stats == stats(incomplete=1, broken=1)


@pytest.mark.parametrize(
    "sequence",
    [
        pytest.param([DT1, DT1, DT2, DT3], id="duplicate"),
        pytest.param([DT1, DT3], id="gap"),
        pytest.param([DT2, DT1, DT3], id="swapped"),
        pytest.param([DT1, DT3, DT2], id="swapped-last"),
        pytest.param([b"\x00" + DT1[1:], DT1, DT2, DT3], id="sequence-0"),
        pytest.param([DT1, b"\x02", DT2, DT3], id="dt-without-data"),
        pytest.param([DT1, b"", DT2, DT3], id="empty-dt"),
        pytest.param([DT1, DT2[:7], DT3], id="middle-packet-short"),
        pytest.param([DT1, DT2, DT3[:2]], id="last-packet-short"),
    ],
)
def test_sequence_faults_break_the_transfer(sequence: list[bytes]) -> None:
    r = BamReassembler()
    frames = [(CM_ID, CM), *((DT_ID, data) for data in sequence)]
    assert feed_all(r, frames) == []
    assert r.stats == stats(broken=1)
    assert r.pending() == 0


def test_last_packet_needs_only_its_bytes() -> None:
    r = BamReassembler()
    assert feed_all(r, [FRAMES[0], FRAMES[1], FRAMES[2], (DT_ID, DT3[:6])])[0].payload == PAYLOAD


def test_orphan_packets() -> None:
    r = BamReassembler()
    assert feed_all(r, FRAMES[1:]) == []
    assert r.stats == stats(broken=3, orphan_packets=3)
    # A repeat of the last packet after completion has nothing to belong to.
    r = BamReassembler()
    assert len(feed_all(r, [*FRAMES, FRAMES[3]])) == 1
    assert r.stats == stats(completed=1, broken=1, orphan_packets=1)


def test_gap_longer_than_t1_is_incomplete() -> None:
    r = BamReassembler()
    assert feed(r, 0.0, CM_ID, CM) is None
    assert feed(r, 0.5, DT_ID, DT1) is None
    assert feed(r, 1.26, DT_ID, DT2) is None
    assert feed(r, 1.3, DT_ID, DT3) is None
    assert r.stats == stats(incomplete=1)
    assert r.pending() == 0
    # Much later, a packet with no announcement is an orphan.
    assert feed(r, 5.0, DT_ID, DT1) is None
    assert r.stats == stats(incomplete=1, broken=1, orphan_packets=1)


def test_gap_of_exactly_t1_is_allowed() -> None:
    r = BamReassembler(t1=0.5)
    assert feed_all(r, FRAMES, step=0.5)[0].payload == PAYLOAD


def test_custom_t1() -> None:
    r = BamReassembler(t1=0.1)
    assert feed_all(r, FRAMES, step=0.2) == []
    # DT1 comes too late for the announcement; DT2 and DT3 too late even to be its tail.
    assert r.stats == stats(incomplete=1, broken=2, orphan_packets=2)


def test_expire() -> None:
    r = BamReassembler()
    feed(r, 0.0, CM_ID, CM, "can0")
    feed(r, 0.5, CM_ID, CM, "can1")
    assert r.pending() == 2
    assert r.expire(0.75) == 0
    assert r.expire(0.76) == 1
    assert r.pending() == 1
    assert r.stats == stats(incomplete=1)
    # A late packet of the expired transfer is part of it, not an orphan...
    assert feed(r, 0.8, DT_ID, DT1, "can0") is None
    assert r.stats == stats(incomplete=1)
    assert r.expire(10.0) == 1
    assert r.pending() == 0
    # ...but one long after is.
    assert feed(r, 20.0, DT_ID, DT1, "can0") is None
    assert r.stats == stats(incomplete=2, broken=1, orphan_packets=1)


def test_announcement_after_a_fault_starts_cleanly() -> None:
    r = BamReassembler()
    frames = [FRAMES[0], FRAMES[2], *FRAMES]
    assert feed_all(r, frames)[0].payload == PAYLOAD
    assert r.stats == stats(completed=1, broken=1)


# --- properties ---------------------------------------------------------------------------


@settings(deadline=None)
@given(
    pgn=st.integers(0, 0x3FFFF),
    payload=st.binary(min_size=9, max_size=1785),
    sa=st.integers(0, 255),
    channel=st.one_of(st.none(), st.sampled_from(["can0", "vcan1"])),
)
def test_encode_then_reassemble(pgn: int, payload: bytes, sa: int, channel: str | None) -> None:
    frames = encode_bam(pgn, payload, sa=sa)
    assert len(frames) == 1 + -(-len(payload) // 7)
    assert all(len(data) == 8 for _, data in frames)
    r = BamReassembler()
    transfers = feed_all(r, frames, step=0.01, channel=channel)
    assert transfers == [Transfer(0.01 * (len(frames) - 1), channel, sa, pgn, payload)]
    assert r.stats == stats(completed=1) and r.pending() == 0


@given(
    st.lists(
        st.tuples(
            st.floats(0, 5, allow_nan=False),
            st.sampled_from([PGN_TP_CM, PGN_TP_DT]),
            st.sampled_from([0x1E, 0x1F]),
            st.sampled_from([0xFF, 0x41]),
            st.binary(max_size=9),
        ),
        max_size=40,
    )
)
def test_arbitrary_frames_never_raise(
    frames: list[tuple[float, int, int, int, bytes]],
) -> None:
    r = BamReassembler()
    for ts, pgn, sa, da, data in frames:
        transfer = r.feed(ts, "can0", sa, da, pgn, data)
        if transfer is not None:
            assert 9 <= len(transfer.payload) <= 1785
    r.expire(100.0)
    assert r.pending() == 0
    s = r.stats
    assert min(s.completed, s.incomplete, s.broken, s.orphan_packets) >= 0


@dataclass(frozen=True)
class Sent:
    """One frame as sent: which stream, which transfer of it, which frame of that transfer."""

    key: int
    transfer: int
    index: int
    can_id: int
    data: bytes


KEYS = [("can0", 0x1E), ("can0", 0x2A), ("can1", 0x1E)]
OPS = st.lists(st.tuples(st.sampled_from(["drop", "dup", "swap"]), st.integers(0, 99)), max_size=4)


def corrupt(frames: list[Sent], ops: list[tuple[str, int]]) -> list[Sent]:
    out = list(frames)
    for op, at in ops:
        if not out:
            break
        i = at % len(out)
        if op == "drop":
            del out[i]
        elif op == "dup":
            out.insert(i, out[i])
        else:
            j = (i + 1) % len(out)
            out[i], out[j] = out[j], out[i]
    return out


def intact_runs(received: list[Sent], frame_count: int) -> int:
    """How often the whole transfer arrives as CM, DT 1..n with nothing of its own in between."""
    wanted = list(range(frame_count))
    indexes = [f.index for f in received]
    return sum(
        indexes[i : i + frame_count] == wanted for i in range(len(indexes) - frame_count + 1)
    )


@settings(max_examples=300, deadline=None)
@given(data=st.data(), expire_as_we_go=st.booleans())
def test_only_whole_in_order_transfers_are_emitted(
    data: st.DataObject, expire_as_we_go: bool
) -> None:
    timeline: list[tuple[float, int, int, Sent]] = []
    expected: dict[int, list[tuple[int, bytes]]] = {k: [] for k in range(len(KEYS))}
    for key, (_, sa) in enumerate(KEYS):
        offset = data.draw(st.floats(0, 0.5), label="offset")
        spacing = data.draw(st.floats(0.001, 0.05), label="spacing")
        for transfer in range(data.draw(st.integers(1, 3), label="transfers")):
            pgn = data.draw(st.sampled_from([PGN_DM1, 0xFEEB, 0xFEDA]), label="pgn")
            payload = data.draw(st.binary(min_size=9, max_size=60), label="payload")
            sent = [
                Sent(key, transfer, i, can_id, frame)
                for i, (can_id, frame) in enumerate(encode_bam(pgn, payload, sa=sa))
            ]
            received = corrupt(sent, data.draw(OPS, label="corruption"))
            expected[key] += [(pgn, payload)] * intact_runs(received, len(sent))
            # Transfers of one stream are 2 s apart, as a DM1 repeats: any packet of one that
            # survives never gets within t1 of the next, so two transfers cannot merge.
            start = offset + 2.0 * transfer
            timeline += [(start + spacing * i, key, i, f) for i, f in enumerate(received)]
    timeline.sort(key=lambda item: item[:3])

    r = BamReassembler()
    emitted: dict[int, list[tuple[int, bytes]]] = {k: [] for k in range(len(KEYS))}
    for ts, key, _, frame in timeline:
        if expire_as_we_go:
            r.expire(ts)
        channel, sa = KEYS[key]
        j = parse_id(frame.can_id)
        transfer = r.feed(ts, channel, j.sa, j.da, j.pgn, frame.data)
        if transfer is not None:
            assert (transfer.channel, transfer.sa, transfer.ts) == (channel, sa, ts)
            emitted[key].append((transfer.pgn, transfer.payload))
    assert emitted == expected
    r.expire((timeline[-1][0] if timeline else 0.0) + 1.0)
    assert r.pending() == 0
    assert r.stats.completed == sum(len(v) for v in expected.values())
