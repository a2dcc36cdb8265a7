"""web: what every domain's routes share, below the domains (it imports none of them).

`runtime.py` (`Runtime`, the running gateway a route reaches as `rt: Rt`; the domains'
services it carries are named for their types only), `errors.py` (`ApiError` and the one error
body), `responses.py` (JSON responses), `schemas.py` (`RequestBody`, `errors(...)` for a route's
documented error answers), `settings.py` (`ApiSettings`), `times.py` (times in query
parameters), `csv_export.py` (CSV answers streamed in keyset pages). Who may call a route is
`eqgw.security.auth`'s; the shapes of a domain's answers are the domain's own.
"""
