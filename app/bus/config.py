"""Configuration of one CAN bus: which python-can interface, which vehicle, which equalizers."""

from __future__ import annotations

from typing import Any

from pydantic import BaseModel, ConfigDict, Field, field_validator


class BusConfig(BaseModel):
    """One vehicle bus. `interface`/`channel`/`bitrate` and `options` go to `can.Bus(...)`."""

    model_config = ConfigDict(extra="forbid")

    name: str = Field(description="Stable bus name, unique in the fleet, e.g. 'BUS-101/can0'")
    vehicle_id: str
    interface: str = Field(description="python-can interface: socketcan, socketcand, virtual, ...")
    channel: str
    bitrate: int | None = 250_000
    options: dict[str, Any] = Field(
        default_factory=dict, description="Extra keyword arguments for can.Bus (host, port, ...)"
    )
    equalizer_sas: list[int] = Field(default_factory=lambda: [0x1E])
    gateway_sa: int = 0xD8
    # J1939-21 order is least significant byte first; a unit that proves otherwise gets "msb".
    request_byte_order: str = "lsb"

    @field_validator("equalizer_sas")
    @classmethod
    def _sas_valid(cls, v: list[int]) -> list[int]:
        if not v:
            raise ValueError("at least one equalizer source address is required")
        for sa in v:
            if not 0 <= sa <= 253:
                raise ValueError(f"source address {sa} is not 0..253")
        if len(set(v)) != len(v):
            raise ValueError("equalizer source addresses must be unique on a bus")
        return v

    @field_validator("gateway_sa")
    @classmethod
    def _gw_valid(cls, v: int) -> int:
        if not 0 <= v <= 253:
            raise ValueError(f"gateway source address {v} is not 0..253")
        return v

    @field_validator("request_byte_order")
    @classmethod
    def _order_valid(cls, v: str) -> str:
        if v not in ("lsb", "msb"):
            raise ValueError("request_byte_order is 'lsb' (J1939-21) or 'msb'")
        return v
