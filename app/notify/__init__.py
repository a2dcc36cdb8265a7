"""notify: where alerts and telemetry go (webhooks, email, Teams, PagerDuty, MQTT).

`delivery.py` (the `alert_events` outbox to every destination: claims, order, retries),
`senders.py` (one attempt per destination format), `webhooks.py` (bodies and signatures),
`destinations.py` (which addresses a destination may have), `guarded.py` (the HTTP client that
connects only there; loaded at the first delivery), `mqtt.py` (the outbox to MQTT, and
the broker connection the telemetry shares), `telemetry.py` (live values, vehicle states and
the gateway's availability to MQTT, Home Assistant discovery), `repository.py` (webhooks,
their outbox and cursors), `endpoints.py` (webhook administration).
"""
