"""Settings of a gateway among several on one PostgreSQL; `EQGW_CLUSTER_...` variables."""

from __future__ import annotations

import os
import socket
from typing import Literal

from pydantic import Field, model_validator
from pydantic_settings import BaseSettings, SettingsConfigDict


def default_instance_id() -> str:
    """hostname-pid: unique among running gateways, readable in pg_stat_activity."""
    return f"{socket.gethostname()}-{os.getpid()}"


class ClusterSettings(BaseSettings):
    """Leases and fan-out; only used on PostgreSQL (on SQLite one gateway owns every bus)."""

    model_config = SettingsConfigDict(env_prefix="EQGW_CLUSTER_", extra="ignore")

    mode: Literal["auto", "off"] = Field(
        default="auto",
        description="auto: leases and fan-out on PostgreSQL; off: read every configured bus",
    )
    instance_id: str = Field(default_factory=default_instance_id, min_length=1, max_length=40)
    lease_period_s: float = Field(
        default=2.0, gt=0, le=60, description="How often free buses are taken and leases checked"
    )
    lease_timeout_s: float = Field(
        default=3.0,
        gt=0,
        le=60,
        description="A lease check slower than this fences the gateway (no command delivery)",
    )
    lease_ttl_s: float = Field(
        default=8.0,
        gt=0,
        le=60,
        description="The server ends a lease session it has heard nothing from for this long "
        "(idle_session_timeout), freeing its buses for the others",
    )
    fence_margin_s: float = Field(
        default=2.0,
        gt=0,
        description="A gateway stops sending on its buses this long before its lease can have "
        "expired for the others, by its own clock",
    )
    keepalive_idle_s: int = Field(
        default=3, ge=1, description="Server-side TCP keepalive of the lease connection"
    )
    keepalive_interval_s: int = Field(default=2, ge=1)
    keepalive_count: int = Field(default=3, ge=1)
    rebalance: bool = Field(
        default=True,
        description="Hand buses over to gateways with fewer (each move leaves a gap of about "
        "one lease period on that bus)",
    )
    unreachable_s: float = Field(
        default=10.0,
        gt=0,
        description="A bus this gateway has failed to open for this long goes to another "
        "gateway (one that may reach it); it may come back after a few lease periods",
    )
    mirror_refresh_s: float = Field(
        default=30.0, gt=0, description="Reload other gateways' units from the database"
    )

    @model_validator(mode="after")
    def _timing(self) -> ClusterSettings:
        if self.takeover_bound_s > 15.0:
            raise ValueError(
                f"lease timing gives a takeover bound of {self.takeover_bound_s:g} s; keep it "
                "under 15 s (shorter lease_period_s, lease_ttl_s or keepalive settings)"
            )
        if self.fence_bound_s > self.fence_after_s:
            # Healthy rounds must confirm the lease before the gateway's clock fences it.
            raise ValueError(
                f"lease_period_s + lease_timeout_s ({self.fence_bound_s:g} s) must not exceed "
                f"the time after which a gateway fences itself ({self.fence_after_s:g} s: "
                "lease_ttl_s, or the server's dead-peer detection if shorter, minus "
                "fence_margin_s)"
            )
        return self

    @property
    def dead_peer_s(self) -> float:
        """How long PostgreSQL takes to drop the lease connection of an unreachable host."""
        return self.keepalive_idle_s + self.keepalive_interval_s * self.keepalive_count

    @property
    def expiry_s(self) -> float:
        """The earliest the server may free a gateway's locks after it last heard from it:
        its idle session timeout, or its TCP keepalive giving up on the host."""
        return min(self.lease_ttl_s, self.dead_peer_s)

    @property
    def fence_after_s(self) -> float:
        """A gateway whose lease was last confirmed this long ago (by its own clock, from when
        it sent the round that confirmed it) stops sending on every bus."""
        return self.expiry_s - self.fence_margin_s

    @property
    def fence_bound_s(self) -> float:
        """How long a healthy round may take to confirm the lease after the previous one."""
        return self.lease_period_s + self.lease_timeout_s

    @property
    def takeover_bound_s(self) -> float:
        """Worst case from a gateway's death to another one reading its buses: the server
        frees the locks (at once for a dead process, `expiry_s` for a silent one), then the
        next lease round (`lease_period_s`) takes them, plus the round's own time."""
        return self.expiry_s + self.lease_period_s + self.lease_timeout_s
