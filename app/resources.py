"""Where the files shipped with the package live: the Alembic migrations and the dashboard.

In a checkout they sit beside the package folder (`migrations/`, `static/` at the top); an
installed wheel carries them inside the package (`<package>/migrations`, `<package>/static`).
Neither depends on the current directory.
"""

from __future__ import annotations

from pathlib import Path

PACKAGE_DIR = Path(__file__).resolve().parent


def shipped_dir(name: str) -> Path:
    """The folder `name` (`migrations` or `static`) inside the package, else beside it."""
    inside = PACKAGE_DIR / name
    if inside.is_dir():
        return inside
    return PACKAGE_DIR.parent / name


def migrations_dir() -> Path:
    """The Alembic script folder (env.py, versions/)."""
    return shipped_dir("migrations")


def static_dir() -> Path:
    """The dashboard's files (index.html, css/, js/, vendor/)."""
    return shipped_dir("static")
