"""alerts: rules over each unit's live data and faults, alerts with a lifecycle, mutes.

`rules.py` (pure: conditions, hysteresis, delays, the state machine), `engine.py` (evaluates the
rules on ingest events and on a tick, raises/clears alerts), `repository.py` (the alert tables;
every change appends its `alert_events` outbox row in the same transaction), `endpoints.py`
(list, acknowledge, rules, mutes), `schemas.py`, `config.py` (the rules a gateway starts with).
Where an alert goes once raised is `eqgw.notify`'s job.
"""
