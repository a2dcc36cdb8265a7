"""The fleet's tables: each vehicle's buses, and the fleet's version (the `vehicles` table
itself is eqgw.store.models.Vehicle, which the time series refer to)."""

from __future__ import annotations

from typing import Any

from sqlalchemy import BigInteger, Boolean, Double, ForeignKey, Integer, String
from sqlalchemy.orm import Mapped, mapped_column

from eqgw.store.models import Base, JsonType


class VehicleBus(Base):
    """One CAN bus of a vehicle, as eqgw.bus.config.BusConfig describes it (validated by it on
    the way in and out). The NAME the gateway claims its address with is stored only when the
    bus names its own; otherwise each gateway derives it from its `[address_claim]`."""

    __tablename__ = "vehicle_buses"

    name: Mapped[str] = mapped_column(String(200), primary_key=True)
    vehicle_id: Mapped[str] = mapped_column(ForeignKey("vehicles.id"), index=True)
    interface: Mapped[str] = mapped_column(String(64))
    channel: Mapped[str] = mapped_column(String(200))
    bitrate: Mapped[int | None] = mapped_column(Integer)
    options: Mapped[dict[str, Any]] = mapped_column(JsonType)
    equalizer_sas: Mapped[list[int]] = mapped_column(JsonType)
    gateway_sa: Mapped[int] = mapped_column(Integer)
    request_byte_order: Mapped[str] = mapped_column(String(8))
    address_claim: Mapped[bool] = mapped_column(Boolean)
    # 64 bits unsigned do not fit a BIGINT: kept as 0x hex text, as the fleet file takes it.
    address_claim_name: Mapped[str | None] = mapped_column(String(20))
    stall_after_s: Mapped[float] = mapped_column(Double)
    updated_at: Mapped[float] = mapped_column(Double)


class FleetRevision(Base):
    """One row: the fleet's version, raised by every change of a vehicle or bus in the same
    transaction; gateways poll it to follow the fleet. No row: the fleet was never seeded."""

    __tablename__ = "fleet_revision"

    id: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=False)
    version: Mapped[int] = mapped_column(BigInteger)
    changed_at: Mapped[float] = mapped_column(Double)
    seeded_at: Mapped[float] = mapped_column(Double)
    seeded_from: Mapped[str] = mapped_column(
        String(200), doc="what first filled the fleet: the fleet file, the API, an import"
    )
