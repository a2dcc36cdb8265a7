"""Alerting: rules over each unit's live data and faults, alerts with a lifecycle, mutes."""
