"""Settings of the HTTP service (address, command queue, limits); `EQGW_API_...` variables."""

from __future__ import annotations

from pydantic import Field
from pydantic_settings import BaseSettings, SettingsConfigDict


class ApiSettings(BaseSettings):
    """What `eqgw serve` needs beyond the ingest settings; validated at start."""

    model_config = SettingsConfigDict(env_prefix="EQGW_API_", extra="ignore")

    host: str = "127.0.0.1"
    port: int = Field(default=8000, ge=0, le=65535)
    public_url: str | None = Field(
        default=None, description="Base URL printed in the login link (default http://host:port)"
    )
    command_expiry_s: float = Field(default=30.0, gt=0, le=3600)
    command_max_expiry_s: float = Field(default=300.0, gt=0, le=86400)
    resend_interval_s: float = Field(default=1.0, gt=0, description="The manuals' 1 s repeat")
    parameter_sends: int = Field(default=3, ge=1, le=60, description="Sends of a parameter write")
    request_sends: int = Field(default=3, ge=1, le=60, description="Sends of an unanswered request")
    delivery_poll_s: float = Field(default=0.1, gt=0)
    write_rate: int = Field(default=30, ge=1, description="Writes a key may make per window")
    write_window_s: float = Field(default=60.0, gt=0)
    ws_queue: int = Field(default=2000, ge=1, description="Events a websocket may fall behind")
    ws_send_timeout_s: float = Field(default=5.0, gt=0)
    shutdown_timeout_s: float = Field(
        default=9.0,
        ge=3.0,
        description="SIGTERM to exit at most (Docker's default stop timeout is 10 s); the "
        "final flush of the ingest gets what is left of it",
    )
    key_cache_s: float = Field(default=5.0, ge=0, description="How long a key lookup is reused")
    db_deadline_s: float = Field(
        default=3.0,
        gt=0,
        description="A request's database work ends within this (else 503 with Retry-After)",
    )
    import_deadline_s: float = Field(
        default=60.0,
        gt=0,
        description="The database work of a CSV import of vehicles (POST /vehicles/import), "
        "one transaction however many rows, ends within this",
    )
    audit_retention_days: float = Field(
        default=365.0, ge=0, description="Audit entries older than this are deleted; 0 = kept"
    )
    fleet_cache_s: float = Field(default=2.0, ge=0)
    live_cache_s: float = Field(
        default=0.5,
        ge=0,
        description="How long a rendered fleet listing (GET /vehicles) is reused; 0 = never",
    )
    history_cache_buckets: int = Field(
        default=200_000,
        ge=0,
        description="Sealed rollup buckets kept for history reads, checked against the "
        "database on every use (about 340 bytes each); 0 = no cache",
    )
    # Security (docs/security.md).
    session_max_age_s: float = Field(
        default=7 * 86400, gt=0, description="How long a dashboard login lasts (then log in again)"
    )
    login_code_ttl_s: float = Field(
        default=600.0,
        ge=10,
        le=3600,
        description="How long a one-time login link works (eqgw serve's first, eqgw keys "
        "login-link)",
    )
    max_body_bytes: int = Field(
        default=1024 * 1024, ge=1024, description="Largest request body (413 past it)"
    )
    ingest_max_body_bytes: int = Field(
        default=16 * 1024 * 1024, ge=1024, description="Largest forwarder upload (as sent)"
    )
    header_timeout_s: float = Field(
        default=10.0, gt=0, description="A request's headers must arrive within this"
    )
    body_timeout_s: float = Field(
        default=60.0, gt=0, description="A request's body must arrive within this"
    )
    ws_control_queue: int = Field(
        default=64, ge=1, description="Replies a websocket client may have waiting (then closed)"
    )
    ws_max_per_key: int = Field(
        default=32,
        ge=1,
        description="Websockets one key (and its browser sessions) may hold open; the next is "
        "refused (close code 4429)",
    )
    ws_max_per_client: int = Field(
        default=64,
        ge=1,
        description="Websockets one client address may hold open, with or without a key; the "
        "next is refused (close code 4429)",
    )
    metrics_token: str | None = Field(
        default=None,
        description="Bearer token that reads /metrics and /readyz details (besides admin keys)",
    )
    docs: bool = Field(default=True, description="Serve /docs and /openapi.json")
