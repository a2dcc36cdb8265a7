"""fleet: vehicles, their buses and their diagnosis.

`endpoints.py` (the fleet, a vehicle's live values, history and faults), `schemas.py` (their
answers; the management routes' bodies and answers), `diagnosis.py` (the
manuals' troubleshooting table and the one imbalance computation, pure); the fleet kept in the
database: `models.py` (its tables), `repository.py` (its SQL), `registry.py` (seeding from the
fleet file, every change checked and made in one transaction), `importer.py` (CSV),
`management.py` (the routes that add, change, delete and import vehicles), `sync.py` (a
running gateway following the fleet), `cli.py` (`eqgw vehicles`).
"""
