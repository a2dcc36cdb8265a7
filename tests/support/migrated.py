"""An SQLite database migrated once per test process and copied into each test's own file.

A migration of an empty SQLite file takes 0.1 s of CPU and 0.3-0.7 s in all (its commits wait
for the disk); a copy takes a millisecond. On PostgreSQL the server's own work dominates (DDL of
~50 tables and their partitions): replaying a dump of a migrated schema took as long as the
migration, so PostgreSQL schemas are still migrated one by one.

The chain itself stays tested where it is the subject (tests/test_vehicles_migration.py,
tests/test_partitions.py, every gateway started on an empty database) and here: the template
is made by `upgrade_engine`, and the engine fixture runs `upgrade_engine` again on the copy,
which finds it at the head revision."""

from __future__ import annotations

import shutil
import threading
from pathlib import Path

from eqgw.store.engine import create_engine
from eqgw.store.migrate import upgrade_engine

_lock = threading.Lock()
_template: Path | None = None


def copy_migrated_sqlite(target: Path, scratch: Path) -> None:
    """Make `target` (an SQLite file not written yet) a copy of a freshly migrated database,
    migrated into `scratch` (a folder that outlives the test) the first time."""
    global _template
    if target.exists() and target.stat().st_size > 0:
        raise AssertionError(f"{target} is not empty: a migrated copy would overwrite it")
    with _lock:
        if _template is None:
            path = scratch / "eqgw.db"
            engine = create_engine(f"sqlite:///{path}")
            try:
                upgrade_engine(engine)
            finally:
                engine.dispose()  # the last connection checkpoints the WAL into the file
            _template = path
    # shutil.copy keeps the file's mode: the gateway makes its database private (0600).
    shutil.copy(_template, target)
