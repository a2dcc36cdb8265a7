"""Configuration of one CAN bus: which python-can interface, which vehicle, which equalizers."""

from __future__ import annotations

from typing import Any

from pydantic import BaseModel, ConfigDict, Field, field_validator


def parse_name(v: Any) -> Any:
    """A J1939 NAME given as text ("0x10FF00000001B3FC", as TOML integers stop at 2**63)."""
    if isinstance(v, str):
        try:
            return int(v.strip().replace("_", ""), 0)
        except ValueError:
            raise ValueError(f"{v!r} is not an integer (decimal or 0x hex)") from None
    return v


def check_gateway_name(name: int, what: str) -> None:
    """ValueError unless `name` is a NAME the gateway can claim with: 64 bits, and not
    arbitrary-address capable (the gateway does not pick another address when it loses)."""
    if not 0 <= name < 1 << 64:
        raise ValueError(f"{what}: a J1939 NAME is a 64-bit unsigned integer")
    if name >> 63:
        raise ValueError(
            f"{what}: 0x{name:016X} says 'arbitrary address capable' (bit 63); the gateway "
            "is not: it keeps gateway_sa or stops transmitting"
        )


def _interfaces(schema: dict[str, Any]) -> None:
    """The schema of `interface`: python-can's interfaces (imported when a schema is made)."""
    import can

    schema["enum"] = sorted(can.interfaces.VALID_INTERFACES)


class BusConfig(BaseModel):
    """One vehicle bus. `interface`/`channel`/`bitrate` and `options` go to `can.Bus(...)`."""

    model_config = ConfigDict(extra="forbid")

    name: str = Field(
        min_length=1,
        max_length=200,
        description="Stable bus name, unique in the fleet, e.g. 'BUS-101/can0'",
    )
    vehicle_id: str
    interface: str = Field(
        description="python-can interface: socketcan, socketcand, virtual, ...",
        json_schema_extra=_interfaces,
    )
    channel: str = Field(min_length=1, max_length=200)
    bitrate: int | None = Field(default=250_000, gt=0)
    options: dict[str, Any] = Field(
        default_factory=dict, description="Extra keyword arguments for can.Bus (host, port, ...)"
    )
    equalizer_sas: list[int] = Field(
        default_factory=lambda: [0x1E],
        description="Source addresses of the equalizers on the bus (30 = 0x1E by default)",
        json_schema_extra={
            "items": {"type": "integer", "minimum": 0, "maximum": 253},
            "minItems": 1,
            "uniqueItems": True,
        },
    )
    gateway_sa: int = Field(
        default=0xD8,
        description="The gateway's own source address on the bus",
        json_schema_extra={"minimum": 0, "maximum": 253},
    )
    # J1939-21 order is least significant byte first; a unit that proves otherwise gets "msb".
    request_byte_order: str = Field(default="lsb", json_schema_extra={"enum": ["lsb", "msb"]})
    # The 64-bit J1939 NAME the gateway claims `gateway_sa` with (PGN 60928); None: no claim.
    # Set for every bus by `[address_claim]` (eqgw.config), or per bus.
    address_claim_name: int | None = None
    # False: this bus is never claimed on (the integrator says it has no address management).
    address_claim: bool = True

    @field_validator("address_claim_name", mode="before")
    @classmethod
    def _name_from_text(cls, v: Any) -> Any:
        return parse_name(v)

    @field_validator("address_claim_name")
    @classmethod
    def _name_valid(cls, v: int | None) -> int | None:
        if v is not None:
            check_gateway_name(v, "address_claim_name")
        return v

    # socketcand only: a link that took frames to send while nothing was received for this
    # long is stalled (a frozen server still accepts bytes into its socket buffers); the gateway
    # stops handing it frames until a frame arrives again. Units talk at least every 3 s.
    stall_after_s: float = Field(default=4.0, ge=0, description="0 turns the check off")

    @field_validator("name", "channel")
    @classmethod
    def _printable(cls, v: str) -> str:
        if any(ord(c) < 32 or ord(c) == 127 for c in v):
            raise ValueError("no control characters (newlines, tabs, NUL)")
        return v

    @field_validator("interface")
    @classmethod
    def _interface_known(cls, v: str) -> str:
        import can

        if v not in can.interfaces.VALID_INTERFACES:
            known = ", ".join(sorted(can.interfaces.VALID_INTERFACES))
            raise ValueError(f"{v!r} is not a python-can interface; one of: {known}")
        return v

    @field_validator("options")
    @classmethod
    def _options_valid(cls, v: dict[str, Any]) -> dict[str, Any]:
        # can.Bus(interface=..., channel=..., **options): these two are their own fields.
        clash = sorted(set(v) & {"interface", "channel"})
        if clash:
            raise ValueError(f"{', '.join(clash)} is a field of the bus, not an option")
        for key in v:
            if not key.isidentifier():
                raise ValueError(f"option {key!r} is not a keyword argument name")
        return v

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
