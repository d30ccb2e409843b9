"""Quality logs of an older schema version, for the migration tests.

A log is written by this version, then the columns the later versions added are dropped and
the version put back: the layout an older planer wrote, with the same rows in its columns.
Works on an SQLite connection and on a psycopg one (both have ``execute``).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from controller.quality.schema import columns_added_since


def downgrade(execute: Callable[..., Any], version: int) -> tuple[str, ...]:
    """Make the open log the layout of ``version`` (3 .. current); the columns dropped.

    Parameters
    ----------
    execute : callable
        ``conn.execute`` of an SQLite or psycopg connection to the log (autocommit or
        committed by the caller).
    version : int
        The older schema version to write down.
    """
    later = columns_added_since(version)
    for name, _, _ in reversed(later):
        execute(f"ALTER TABLE records DROP COLUMN {name}")
    execute(f"UPDATE schema_version SET version = {int(version)}")
    return tuple(name for name, _, _ in later)


def old_log(target: Any, records: Any, version: int) -> tuple[str, ...]:
    """Write ``records`` with this version, then make the log the layout of ``version``.

    ``target``: an SQLite file or a ``postgresql://`` URL. Returns the columns dropped.
    """
    from controller.quality.log import QualityLog, is_database_url

    with QualityLog(target) as log:
        for r in records:
            log.append(r)
    if is_database_url(target):
        import psycopg

        with psycopg.connect(str(target), autocommit=True) as conn:
            return downgrade(conn.execute, version)
    import sqlite3

    with sqlite3.connect(target) as conn:
        return downgrade(conn.execute, version)
