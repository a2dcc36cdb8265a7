"""notify: where alerts and telemetry go (webhooks, email, Teams, PagerDuty, MQTT)"""
