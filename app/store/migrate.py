"""Apply the Alembic migrations in `migrations/` to a database URL."""

from __future__ import annotations

from alembic import command
from alembic.config import Config
from alembic.runtime.migration import MigrationContext
from alembic.script import ScriptDirectory
from sqlalchemy import Engine
from sqlalchemy.engine import URL

from eqgw.resources import migrations_dir
from eqgw.store.engine import create_engine, db_deadline
from eqgw.store.errors import MigrationError


def alembic_config(url: str | URL | None = None) -> Config:
    """An Alembic Config for the project's migrations, independent of the current directory."""
    # No alembic.ini: an installed wheel has none, and every option it held is set here.
    cfg = Config()
    cfg.set_main_option("script_location", str(migrations_dir()))
    cfg.set_main_option("path_separator", "os")
    if url is not None:
        # `%` is ConfigParser interpolation: URL-encoded options must be doubled.
        text = url if isinstance(url, str) else url.render_as_string(hide_password=False)
        cfg.set_main_option("sqlalchemy.url", text.replace("%", "%%"))
    return cfg


def upgrade(url: str | URL, revision: str = "head") -> None:
    """Bring the database at `url` to `revision` (the latest by default)."""
    engine = create_engine(url)
    try:
        upgrade_engine(engine, revision)
    finally:
        engine.dispose()


def upgrade_engine(engine: Engine, revision: str = "head") -> None:
    """Bring the database behind an existing engine to `revision`."""
    cfg = alembic_config()
    try:
        # A migration of a large table may take long: no deadline of the client or the server.
        with db_deadline(None), engine.connect() as conn:
            pg = conn.dialect.name == "postgresql"
            if pg:
                conn.exec_driver_sql("SET statement_timeout = 0")
                conn.exec_driver_sql("SET lock_timeout = 0")
                conn.commit()
            cfg.attributes["connection"] = conn
            command.upgrade(cfg, revision)
            conn.commit()
            if pg:  # the session's own deadlines again (set when it connected)
                conn.exec_driver_sql("RESET statement_timeout")
                conn.exec_driver_sql("RESET lock_timeout")
                conn.commit()
    except Exception as exc:
        raise MigrationError(f"migration to {revision} failed: {exc}") from exc


def current_revision(engine: Engine) -> str | None:
    """The revision the database is at, or None for an empty database."""
    with engine.connect() as conn:
        return MigrationContext.configure(conn).get_current_revision()


def head_revision() -> str | None:
    """The latest revision in `migrations/versions`."""
    return ScriptDirectory.from_config(alembic_config()).get_current_head()
