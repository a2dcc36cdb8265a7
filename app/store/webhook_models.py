"""SQLAlchemy models of alert delivery: webhooks, their outbox and delivery log, cursors."""

from __future__ import annotations

from sqlalchemy import Boolean, Double, ForeignKey, Index, Integer, String, UniqueConstraint
from sqlalchemy.orm import Mapped, mapped_column

from eqgw.store.models import Base, JsonType


class Webhook(Base):
    """An HTTP endpoint that receives alert events, signed with its own secret."""

    __tablename__ = "webhooks"

    id: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=True)
    name: Mapped[str] = mapped_column(String(200), unique=True)
    url: Mapped[str] = mapped_column(String(2000))
    # Kept as given: HMAC signing needs the secret itself, not a hash of it.
    secret: Mapped[str] = mapped_column(String(200))
    format: Mapped[str] = mapped_column(
        String(16), doc="json, slack, teams, pagerduty or email (url mailto:)"
    )
    enabled: Mapped[bool] = mapped_column(Boolean)
    min_severity: Mapped[str | None] = mapped_column(String(16), doc="null: every severity")
    kinds: Mapped[list[str] | None] = mapped_column(JsonType, doc="null: every event kind")
    vehicles: Mapped[list[str] | None] = mapped_column(JsonType, doc="null: every vehicle")
    rules: Mapped[list[str] | None] = mapped_column(JsonType, doc="null: every rule")
    created_at: Mapped[float] = mapped_column(Double)
    updated_at: Mapped[float] = mapped_column(Double)


class WebhookDelivery(Base):
    """One alert event for one webhook (the outbox row and its log line); test sends too."""

    __tablename__ = "webhook_deliveries"
    __table_args__ = (
        # Fan-out inserts ignore conflicts on this: an event is queued once per webhook.
        UniqueConstraint("webhook_id", "event_id"),
        Index(None, "state", "next_attempt_at"),
        Index(None, "webhook_id", "created_at"),
    )

    id: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=True)
    webhook_id: Mapped[int] = mapped_column(ForeignKey("webhooks.id", ondelete="CASCADE"))
    event_id: Mapped[int | None] = mapped_column(Integer, doc="alert_events.id; null for a test")
    kind: Mapped[str] = mapped_column(String(16), doc="raised, acknowledged, cleared or test")
    alert_id: Mapped[int | None] = mapped_column(Integer)
    state: Mapped[str] = mapped_column(String(16), doc="pending, delivered or failed")
    attempts: Mapped[int] = mapped_column(Integer)
    created_at: Mapped[float] = mapped_column(Double)
    next_attempt_at: Mapped[float] = mapped_column(Double, doc="also the claim lease while sending")
    last_attempt_at: Mapped[float | None] = mapped_column(Double)
    last_status: Mapped[int | None] = mapped_column(Integer, doc="HTTP status of the last attempt")
    last_error: Mapped[str | None] = mapped_column(String(2000))
    delivered_at: Mapped[float | None] = mapped_column(Double)


class DeliveryCursor(Base):
    """How far a delivery target has read `alert_events` (everything at or below is handled)."""

    __tablename__ = "delivery_cursors"

    name: Mapped[str] = mapped_column(String(32), primary_key=True, doc="webhooks or mqtt")
    last_event_id: Mapped[int] = mapped_column(Integer)
    # A publisher's lease (MQTT): one gateway at a time reads and publishes from the cursor.
    owner: Mapped[str | None] = mapped_column(String(64))
    lease_until: Mapped[float | None] = mapped_column(Double)
    updated_at: Mapped[float] = mapped_column(Double)
