"""Making what was written to disk durable."""

import os
from pathlib import Path


def fsync_path(path: str | Path) -> None:
    """fsync a file, or a directory (so that the names just made in it survive a crash)."""
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)
