"""security: keys, sessions, scopes, audit, the request guard, single sign-on.

`keys.py` (API keys: generation, hashing, cached lookup, roles and scopes of a caller),
`sessions.py` (dashboard logins: a key or a one-time code for an HttpOnly cookie, CSRF, logout),
`login_codes.py`, `auth.py` (who may call a route, declared by a parameter's type:
`who: OperatorWrite`; `vehicle_id: VehicleId` resolved within the caller's scope; refusals audited),
`guard.py` (the middleware every request passes first), `audit.py` (`AuditLog`, the audit row,
anonymous refusals counted, retention), `endpoints.py` (key administration and the audit log,
its CSV), `schemas.py` (key administration's bodies and answers; the answers of `/me`,
`/session`, `/parameters` and the audit log), `me.py` (`/me`, `/parameters`),
`repository.py` (keys and audit rows), `session_repository.py`, `limits.py` and
`limit_repository.py` (the write rate limit shared by every gateway), `oidc.py` (single sign-on:
OpenID Connect, the authorization code flow with PKCE, groups mapped to roles and depots),
`oidc_provider.py` (the provider's discovery, keys, code exchange and ID token checks; loaded
only when single sign-on is set up).
"""
