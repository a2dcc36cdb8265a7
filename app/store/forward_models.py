"""SQLAlchemy model of edge forwarding (issue 8): one row per forwarder stream."""

from __future__ import annotations

from sqlalchemy import BigInteger, Double, Integer, String
from sqlalchemy.orm import Mapped, mapped_column

from eqgw.store.models import Base


class ForwardStream(Base):
    """A forwarder's buffer, as the central service knows it: whose frames, how far acknowledged.

    `acked_seq` is written in the same transaction as the frames' rows, so an acknowledgement
    always means stored, and a batch uploaded again is answered without decoding it twice.
    """

    __tablename__ = "forward_streams"

    stream: Mapped[str] = mapped_column(String(64), primary_key=True, doc="the buffer's uuid")
    vehicle_id: Mapped[str] = mapped_column(String(64))
    bus: Mapped[str] = mapped_column(String(200), doc="the bus name its units are filed under")
    key_id: Mapped[int | None] = mapped_column(
        Integer, doc="the ingest key owning it (the first id of the key's rotations)"
    )
    acked_seq: Mapped[int] = mapped_column(BigInteger, doc="highest sequence number stored")
    frames: Mapped[int] = mapped_column(BigInteger, doc="frames taken (duplicates excluded)")
    dropped: Mapped[int] = mapped_column(BigInteger, doc="frames the forwarder's full buffer lost")
    first_seen: Mapped[float] = mapped_column(Double)
    last_seen: Mapped[float] = mapped_column(Double)
