"""store: the database: engines, every table's model, the time series' writes and reads.

`engine.py` (SQLite and PostgreSQL engines, deadlines), `models.py` and the `*_models.py` files
(every table, one metadata for Alembic), `writes.py` (a batch of time-series rows in one
transaction, idempotent), `queries.py` (history reads), `history_cache.py`, `retention.py`,
`migrate.py`. A domain's own tables are queried from its `repository.py`
(`eqgw.security`, `eqgw.commands`, `eqgw.alerts`, `eqgw.notify`, `eqgw.forward`).
"""
