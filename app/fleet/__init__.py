"""fleet: vehicles, their buses and their diagnosis.

`endpoints.py` (the fleet, a vehicle's live values, history and faults), `diagnosis.py` (the
manuals' troubleshooting table and the one imbalance computation, pure).
"""
