"""Documented shapes of the read endpoints' bodies (fleet, health, session, audit).

The handlers render these bodies themselves (orjson, cached listings), so FastAPI does not
validate them on the way out; the schemas are what the OpenAPI document promises and what the
contract test (tests/test_api_schemathesis.py) checks every answer against.
"""

from __future__ import annotations

from typing import Any

from pydantic import BaseModel, Field

# -- health -------------------------------------------------------------------------------------


class Health(BaseModel):
    """The process answers."""

    status: str


class WriterState(BaseModel):
    """The batched writer."""

    state: str
    pending_rows: int
    lag_s: float | None
    consecutive_failures: int


class DatabaseState(BaseModel):
    """Whether the database answers and takes writes."""

    ok: bool
    error: str | None = None
    writer: WriterState


class BusState(BaseModel):
    """One configured bus."""

    name: str
    state: str
    last_error: str | None


class Readiness(BaseModel):
    """Ready when the database answers and takes writes and some bus is open."""

    ready: bool
    # The details below only with a whole-fleet admin key or the metrics token (a load
    # balancer, and any key scoped to depots or vehicles, sees `ready` alone).
    database: DatabaseState | None = None
    buses: list[BusState] | None = None
    alerts: dict[str, Any] | None = Field(
        default=None, description="the alert engine's state (reported only)"
    )
    delivery: dict[str, Any] | None = Field(
        default=None, description="webhook and MQTT delivery (reported only)"
    )
    telemetry: dict[str, Any] | None = Field(
        default=None, description="MQTT telemetry, when enabled (reported only)"
    )
    cluster: dict[str, Any] | None = Field(
        default=None, description="several gateways on one PostgreSQL: who reads which bus"
    )
    fleet: dict[str, Any] | None = Field(
        default=None,
        description="the fleet's version this gateway runs (vehicles, buses, when applied)",
    )
    warm_up: dict[str, Any] | None = Field(
        default=None,
        description="the API's schemas and route tables built before ready: done, seconds",
    )
