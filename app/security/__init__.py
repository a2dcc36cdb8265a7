"""security: keys, sessions, scopes, audit, the request guard, single sign-on."""
