"""api: the HTTP service that composes the domains, above them (no domain imports it).

`ws.py` (the websocket: every message it sends is built here), `health.py` and `metrics.py`
(`/healthz`, `/readyz` with their answers' shapes, `/metrics`), `exports.py` (fleet-wide CSV of
fault episodes, alerts and the audit log, each streamed by its domain), `lifespan.py` (the
`Runtime` built from the domains' services, being ready to serve), `openapi.py`,
`http_protocol.py` (uvicorn with a header deadline), `warmup.py`, `cli.py` (`eqgw serve`,
`eqgw keys`). The app is `eqgw.main`; what the domains' routes share is `eqgw.web`, below them.
"""
