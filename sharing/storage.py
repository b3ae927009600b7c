"""Durable storage for envelopes: the copy that counts (Redis only caches it)."""

import os

from django.core.files.storage import FileSystemStorage, Storage, storages


class DurableFileSystemStorage(FileSystemStorage):
    """Local disk, with the file and its directory fsync'd before save() returns."""

    def _save(self, name: str, content) -> str:
        name = super()._save(name, content)
        path = self.path(name)
        fd = os.open(path, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)
        dir_fd = os.open(os.path.dirname(path), os.O_RDONLY)
        try:
            os.fsync(dir_fd)
        finally:
            os.close(dir_fd)
        return name


def envelope_storage() -> Storage:
    return storages["envelopes"]
