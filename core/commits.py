"""Commits that survive a power loss before anyone is told they happened.

The embedded default, SQLite in WAL mode with `synchronous=NORMAL` (portal/settings.py), makes a
commit atomic and safe from a crash of the process, but leaves it in the operating system's
page cache: a power loss or a kernel crash can roll back the last commits. Where a client
drops its own copy once told "stored" (a robot's spool, on 201), `commits_durable` writes them
out first: one syncfs of the database's file system, shared with the other threads of this
process that need one at the same time (core.files.filesystem_sync), rather than an fsync per
commit under SQLite's write lock (`synchronous=FULL`). PostgreSQL is durable at commit
(`synchronous_commit`, on by default): nothing to do.
"""

import os

from django.db import DEFAULT_DB_ALIAS, connections

from core.files import filesystem_sync, fsync_path


def commits_durable(using: str = DEFAULT_DB_ALIAS) -> None:
    """Everything this process committed to `using` so far survives a power loss."""
    connection = connections[using]
    if connection.vendor != "sqlite":
        return
    database = os.path.abspath(connection.settings_dict["NAME"])
    if filesystem_sync(os.path.dirname(database)):
        return
    wal = f"{database}-wal"
    fsync_path(wal if os.path.exists(wal) else database)
