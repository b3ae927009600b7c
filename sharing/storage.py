"""Durable storage for envelopes: the copy that counts (Redis only caches it)."""

import ctypes
import os
import sys
from collections.abc import Sequence
from contextlib import suppress
from pathlib import Path

from django.core.files.base import ContentFile
from django.core.files.storage import FileSystemStorage, Storage, storages

from core.files import fsync_path


class DurableFileSystemStorage(FileSystemStorage):
    """Local disk, with the file and its directory fsync'd before save() returns."""

    def _save(self, name: str, content) -> str:
        name = super()._save(name, content)
        path = self.path(name)
        fsync_path(path)
        fsync_path(os.path.dirname(path))
        return name

    def save_durably(self, files: Sequence[tuple[str, bytes]]) -> list[str]:
        """Write new files (each name must not exist) and make them durable together: one
        sync of the file system (Linux syncfs), not two fsyncs a file; all or none."""
        written: list[str] = []
        try:
            for name, data in files:
                path = Path(self.path(name))
                path.parent.mkdir(
                    mode=self.directory_permissions_mode or 0o777, parents=True, exist_ok=True
                )
                fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
                written.append(str(path))
                try:
                    os.write(fd, data)  # envelopes are small: one write takes them whole
                finally:
                    os.close(fd)
                if self.file_permissions_mode is not None:
                    os.chmod(path, self.file_permissions_mode)
            _sync(written, self.location)
        except BaseException:
            for path in written:
                with suppress(OSError):
                    os.remove(path)
            raise
        return [name for name, _ in files]


def envelopes_save(storage: Storage, files: Sequence[tuple[str, bytes]]) -> list[str]:
    """Save each (name, data), durable when this returns; the names they were saved as. A
    failure leaves none of them behind."""
    if isinstance(storage, DurableFileSystemStorage):
        return storage.save_durably(files)
    saved: list[str] = []
    try:
        for name, data in files:
            saved.append(storage.save(name, ContentFile(data)))
    except BaseException:
        for name in saved:
            with suppress(OSError):
                storage.delete(name)
        raise
    return saved


def envelope_storage() -> Storage:
    return storages["envelopes"]


def _syncfs() -> object | None:
    """libc's syncfs(2) where there is one (Linux), else None."""
    if not sys.platform.startswith("linux"):
        return None
    try:
        return ctypes.CDLL(None, use_errno=True).syncfs
    except (OSError, AttributeError):
        return None


_SYNCFS = _syncfs()


def _sync(paths: Sequence[str], location: str) -> None:
    """Make new files and their directory entries durable: one syncfs of the file system that
    holds them, or an fsync of each file and each of their directories."""
    if not paths:
        return
    if _SYNCFS is not None:
        fd = os.open(location, os.O_RDONLY)
        try:
            if _SYNCFS(fd) == 0:
                return
        finally:
            os.close(fd)
    for path in paths:
        fsync_path(path)
    for directory in {os.path.dirname(path) for path in paths}:
        fsync_path(directory)
