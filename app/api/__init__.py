"""api: the HTTP service that composes the domains: the app's shared runtime and dependencies.

`deps.py` (the running gateway `Runtime`, role and scope dependencies, rate limits),
`ws.py` (the websocket: every message it sends is built here), `health.py` and `metrics.py`
(`/healthz`, `/readyz`, `/metrics`), `errors.py` (the one error shape), `openapi.py`,
`schemas.py`/`read_schemas.py` (shared request and response shapes), `exports.py` and
`csv_export.py` (fleet-wide CSV), `http_protocol.py` (uvicorn with a header deadline),
`warmup.py`, `settings.py`, `cli.py` (`eqgw serve`, `eqgw keys`). The app and its lifespan
are `eqgw.main`.
"""
