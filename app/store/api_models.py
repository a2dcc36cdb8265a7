"""SQLAlchemy models of the API's own tables: API keys, the audit log and the command queue."""

from __future__ import annotations

from sqlalchemy import Double, Index, Integer, String, UniqueConstraint, text
from sqlalchemy.orm import Mapped, mapped_column

from eqgw.store.models import Base, JSONDict, JsonType


class ApiKey(Base):
    """An API key: only its SHA-256 is stored; the key itself is shown once, at creation."""

    __tablename__ = "api_keys"

    id: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=True)
    name: Mapped[str] = mapped_column(String(200))
    role: Mapped[str] = mapped_column(String(16), doc="viewer, operator or admin")
    prefix: Mapped[str] = mapped_column(String(32), doc="the key's public start, for listings")
    key_hash: Mapped[str] = mapped_column(String(64), unique=True)
    created_at: Mapped[float] = mapped_column(Double)
    revoked_at: Mapped[float | None] = mapped_column(
        Double, doc="revoked from then on (a rotated key's is the end of its overlap)"
    )
    last_used_at: Mapped[float | None] = mapped_column(Double)
    # The scope: depots (vehicle groups) and vehicles the key may see and command; both
    # null = the whole fleet. An ingest key's scope is the vehicles it may upload for.
    scope_groups: Mapped[list[str] | None] = mapped_column(JsonType)
    scope_vehicles: Mapped[list[str] | None] = mapped_column(JsonType)
    expires_at: Mapped[float | None] = mapped_column(Double, doc="null: never expires")
    lineage: Mapped[int | None] = mapped_column(
        Integer, doc="id of the first key of its rotations (null: its own id)"
    )


class AuditEntry(Base):
    """One attempt to change something (accepted or refused): who, what, when, the outcome."""

    __tablename__ = "audit_log"
    __table_args__ = (Index(None, "ts"), Index(None, "vehicle_id", "ts"))

    id: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=True)
    ts: Mapped[float] = mapped_column(Double)
    key_id: Mapped[int | None] = mapped_column(Integer)
    key_name: Mapped[str | None] = mapped_column(String(200))
    role: Mapped[str | None] = mapped_column(String(16))
    action: Mapped[str] = mapped_column(String(64), doc="e.g. command.control, key.create")
    vehicle_id: Mapped[str | None] = mapped_column(String(64))
    target: Mapped[str | None] = mapped_column(String(200))
    request: Mapped[JSONDict | None] = mapped_column(JsonType)
    outcome: Mapped[str] = mapped_column(String(16), doc="accepted, refused or done")
    status_code: Mapped[int] = mapped_column(Integer)
    detail: Mapped[str | None] = mapped_column(String(2000))
    command_id: Mapped[str | None] = mapped_column(String(36))
    # The person behind a single sign-on session (the provider's subject and their email).
    subject: Mapped[str | None] = mapped_column(String(255))
    email: Mapped[str | None] = mapped_column(String(320))


class Command(Base):
    """A queued command for one unit; a row so that it survives restarts and any owner sends it."""

    __tablename__ = "commands"
    __table_args__ = (
        UniqueConstraint("key_id", "idempotency_key"),
        Index(None, "state"),
        Index(None, "vehicle_id", "created_at"),
    )

    id: Mapped[str] = mapped_column(String(36), primary_key=True)
    kind: Mapped[str] = mapped_column(String(16), doc="control, parameters or request")
    vehicle_id: Mapped[str] = mapped_column(String(64))
    bus: Mapped[str] = mapped_column(String(200))
    sa: Mapped[int] = mapped_column(Integer)
    payload: Mapped[JSONDict] = mapped_column(JsonType)
    state: Mapped[str] = mapped_column(
        String(16),
        doc="queued, sending, confirmed, sent, unconfirmed, refused, failed, expired or cancelled",
    )
    reason: Mapped[str | None] = mapped_column(String(2000))
    created_at: Mapped[float] = mapped_column(Double)
    updated_at: Mapped[float] = mapped_column(Double)
    expires_at: Mapped[float] = mapped_column(Double)
    first_sent_at: Mapped[float | None] = mapped_column(Double)
    last_sent_at: Mapped[float | None] = mapped_column(Double)
    sends: Mapped[int] = mapped_column(Integer, default=0)
    max_sends: Mapped[int] = mapped_column(Integer)
    # Written before the first frame is handed to an interface: set means something of the
    # command may have left, whatever was recorded after.
    handed_at: Mapped[float | None] = mapped_column(Double)
    # Frames handed in sends that did not complete (a send timed out or broke mid-way).
    frames_handed: Mapped[int] = mapped_column(Integer, default=0, server_default=text("0"))
    key_id: Mapped[int | None] = mapped_column(Integer)
    key_name: Mapped[str | None] = mapped_column(String(200))
    idempotency_key: Mapped[str | None] = mapped_column(String(200))
