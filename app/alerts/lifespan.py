"""The alert engine of a running gateway, as a part of the lifespan (see app/main.py)."""

from __future__ import annotations

from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from typing import TYPE_CHECKING

from eqgw.alerts.engine import AlertEngine, start_alert_engine

if TYPE_CHECKING:
    from sqlalchemy import Engine

    from eqgw.config import Settings
    from eqgw.ingest.service import IngestService


@asynccontextmanager
async def alerting(
    settings: Settings, engine: Engine, ingest: IngestService
) -> AsyncIterator[AlertEngine | None]:
    """The rules evaluated on the ingest's events (None when `alerts.enabled` is false)."""
    alerts = await start_alert_engine(settings, engine, ingest)
    try:
        yield alerts
    finally:
        if alerts is not None:
            await alerts.stop()
