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
                "under 15 s (shorter lease_period_s or keepalive settings)"
            )
        if self.fence_bound_s >= self.dead_peer_s:
            # A gateway cut off from the database must stop sending commands before the
            # server frees its locks, or two gateways could drive one bus for a moment.
            raise ValueError(
                f"lease_period_s + lease_timeout_s ({self.fence_bound_s:g} s) must be shorter "
                f"than the server's dead-peer detection ({self.dead_peer_s:g} s)"
            )
        return self

    @property
    def dead_peer_s(self) -> float:
        """How long PostgreSQL takes to drop the lease connection of an unreachable host."""
        return self.keepalive_idle_s + self.keepalive_interval_s * self.keepalive_count

    @property
    def fence_bound_s(self) -> float:
        """Worst case from losing the database to this gateway no longer sending on any bus."""
        return self.lease_period_s + self.lease_timeout_s

    @property
    def takeover_bound_s(self) -> float:
        """Worst case from a gateway's death to another one reading its buses: the server
        frees the locks (at once for a dead process, `dead_peer_s` for a lost host), then the
        next lease round (`lease_period_s`) takes them, plus the round's own time."""
        return self.dead_peer_s + self.lease_period_s + self.lease_timeout_s
