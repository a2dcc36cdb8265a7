"""Where alerts and telemetry go, as parts of a running gateway's lifespan (app/main.py)."""

from __future__ import annotations

from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from typing import TYPE_CHECKING

from eqgw.notify.delivery import AlertDelivery

if TYPE_CHECKING:
    from prometheus_client import CollectorRegistry
    from sqlalchemy import Engine

    from eqgw.cluster.settings import ClusterSettings
    from eqgw.config import Settings
    from eqgw.ingest.service import IngestService
    from eqgw.notify.telemetry import TelemetryPublisher
    from eqgw.supervisor import Supervisor


@asynccontextmanager
async def delivering(
    engine: Engine, settings: Settings, public_url: str, registry: CollectorRegistry
) -> AsyncIterator[AlertDelivery]:
    """The outbox to webhooks and MQTT, its counters scraped. Entered before the alert engine
    starts: MQTT's cursor exists, so every event raised from then on is published."""
    delivery = AlertDelivery(engine, settings, public_url)
    await delivery.prepare()
    await delivery.start(registry)
    try:
        yield delivery
    finally:
        await delivery.stop()


@asynccontextmanager
async def telemetry(
    settings: Settings,
    cluster: ClusterSettings,
    ingest: IngestService,
    tasks: Supervisor,
    registry: CollectorRegistry,
) -> AsyncIterator[TelemetryPublisher | None]:
    """MQTT telemetry when enabled (else None): connected, its loop supervised (reported, not
    a readiness condition), its counters scraped; at the end the loop first, then `offline`
    said and the connection closed."""
    if not settings.mqtt.telemetry.enabled:
        yield None
        return
    from eqgw.notify.telemetry import TelemetryPublisher, gateway_id

    def names(vehicle_id: str) -> tuple[str, str | None]:
        v = settings.vehicle(vehicle_id)
        return (vehicle_id, None) if v is None else (v.display_name, v.depot)

    explicit = cluster.instance_id if "instance_id" in cluster.model_fields_set else None
    publisher = TelemetryPublisher(
        settings.mqtt,
        gateway_id(settings.mqtt.telemetry.gateway_id, explicit),
        ingest.hub,
        ingest.live,
        owned_buses=lambda: [*ingest.reading(), *ingest.live.attached],
        vehicle_names=names,
        not_reporting_after_s=settings.monitor.not_reporting_after_s,
        queue=settings.hub.subscriber_queue,
    )
    await publisher.start()
    try:
        registry.register(publisher.collector)
        try:
            async with tasks.running("mqtt telemetry", publisher.run, critical=False):
                yield publisher
        finally:
            registry.unregister(publisher.collector)
    finally:
        await publisher.stop()
