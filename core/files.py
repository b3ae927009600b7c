"""Making what was written to disk durable, and how much room is left on it."""

import ctypes
import os
import sys
import threading
from pathlib import Path


def fsync_path(path: str | Path) -> None:
    """fsync a file, or a directory (so that the names just made in it survive a crash)."""
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def filesystem_free(path: str | Path) -> int:
    """Bytes an unprivileged writer may still use on the file system holding `path`, or its
    nearest parent that exists (a folder made on first use may not be there yet)."""
    path = Path(path).absolute()
    while True:
        try:
            stats = os.statvfs(path)
        except FileNotFoundError:
            if path == path.parent:
                raise
            path = path.parent
        else:
            return stats.f_bavail * stats.f_frsize


def _syncfs() -> object | None:
    """libc's syncfs(2) where there is one (Linux), else None."""
    if not sys.platform.startswith("linux"):
        return None
    try:
        return ctypes.CDLL(None, use_errno=True).syncfs
    except (OSError, AttributeError):
        return None


_SYNCFS = _syncfs()


class _SyncGroup:
    """The syncs of one file system, shared by the threads of this process that need one at
    the same time: a thread's files count as durable once a syncfs that started after they
    were written has finished. A thread that finds one running waits for it and then for
    the next, which the first of the waiters starts for all of them; so a burst of uploads
    costs a few syncs, not one each, and none returns before its own files are synced."""

    def __init__(self, location: str) -> None:
        self.location = location
        self._changed = threading.Condition()
        self._started = 0  # generation of the last sync started
        self._finished = 0  # generation of the last sync finished
        self._running = False
        self._outcomes: dict[int, bool] = {}  # generation: did its syncfs succeed

    def sync(self) -> bool:
        """One syncfs started after this call, finished; whether it succeeded."""
        with self._changed:
            wanted = self._started + 1  # the next sync to start is the first that covers us
            while self._finished < wanted:
                if self._running:
                    self._changed.wait()
                    continue
                self._running = True
                self._started += 1
                generation = self._started
                succeeded = False
                self._changed.release()
                try:
                    succeeded = self._syncfs()
                finally:
                    self._changed.acquire()
                    self._running = False
                    self._finished = generation
                    self._outcomes[generation] = succeeded
                    self._outcomes.pop(generation - _SYNC_OUTCOMES_KEPT, None)
                    self._changed.notify_all()
            return self._outcomes.get(wanted, False)

    def _syncfs(self) -> bool:
        fd = os.open(self.location, os.O_RDONLY)
        try:
            return _SYNCFS(fd) == 0
        finally:
            os.close(fd)


# Outcomes of past syncs kept for threads still to read theirs (each reads within a few).
_SYNC_OUTCOMES_KEPT = 1024
_sync_groups: dict[str, _SyncGroup] = {}
_sync_groups_lock = threading.Lock()


def _sync_group(location: str) -> _SyncGroup:
    with _sync_groups_lock:
        group = _sync_groups.get(location)
        if group is None:
            group = _sync_groups[location] = _SyncGroup(location)
        return group


def filesystem_sync(location: str) -> bool:
    """One syncfs of the file system holding `location`, started after this call and shared
    with the threads of this process that need one at the same time (_SyncGroup); whether it
    ran and succeeded (False where there is no syncfs: fsync what you wrote instead)."""
    return _SYNCFS is not None and _sync_group(location).sync()
