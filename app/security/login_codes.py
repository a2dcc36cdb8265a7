"""One-time dashboard login codes: what the login links of `eqgw serve` (first start) and
`eqgw keys login-link` carry instead of a key.

A code is random (192 bits), stored as SHA-256 with its key and an expiry
(`EQGW_API_LOGIN_CODE_TTL_S`), and used up by the login that exchanges it for a session, on
whichever gateway of the database that happens. The link puts it in the address's fragment
(`/#login=CODE`), which browsers send to no server, proxy or log and never put in a Referer;
the page removes it from the address, says whose key it is, and logs in only when asked to.
"""

from __future__ import annotations

import secrets
import time

from sqlalchemy import Connection

from eqgw.security import session_repository as sq
from eqgw.security.keys import hash_key

LINK_PARAM = "login"


def create_login_code(conn: Connection, key_id: int, ttl_s: float) -> str:
    """A new code logging in as key `key_id` once, within `ttl_s` seconds."""
    code = secrets.token_urlsafe(24)
    sq.add_login_code(conn, code_hash=hash_key(code), key_id=key_id, now=time.time(), ttl_s=ttl_s)
    return code


def login_link(base: str, code: str) -> str:
    """The address a code logs in at: the dashboard, the code in the fragment."""
    return f"{base.rstrip('/')}/#{LINK_PARAM}={code}"
