"""web: what every domain's routes share, below the domains."""
