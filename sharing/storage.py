"""Durable storage for envelopes: the copy that counts (Redis only caches it)."""

import base64
import hashlib
import logging
import os
import threading
from collections.abc import Sequence
from concurrent.futures import Future, ThreadPoolExecutor, wait
from contextlib import suppress
from pathlib import Path
from typing import IO, Any

from boto3.s3.transfer import TransferConfig
from botocore.exceptions import BotoCoreError, ClientError
from django.core.files.base import ContentFile, File
from django.core.files.storage import FileSystemStorage, Storage, storages
from storages.backends.s3 import S3Storage
from storages.utils import clean_name

from core.files import filesystem_sync, fsync_path
from sharing.errors import StorageUnavailable

logger = logging.getLogger(__name__)
# PUTs of one upload in flight together to an S3 server.
S3_PARALLEL_PUTS = 8
# A large file (an export) goes to S3 as a multipart upload of parts this size, two at a
# time: what it holds in memory is about two parts, whatever the file's size.
S3_PART_SIZE = 8 * 1024 * 1024
_S3_TRANSFER = TransferConfig(
    multipart_threshold=S3_PART_SIZE, multipart_chunksize=S3_PART_SIZE, max_concurrency=2
)


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
        written = self.write_new(files)
        try:
            self.sync_written(written)
        except BaseException:
            _paths_remove(written)
            raise
        return [name for name, _ in files]

    def write_new(self, files: Sequence[tuple[str, bytes]]) -> list[str]:
        """Write new files (each name must not exist), not yet durable (`sync_written`); the
        paths written. All or none: a failure removes those written before it."""
        written: list[str] = []
        folders: set[Path] = set()  # made (or found) once per call, not once per file
        mode = self.file_permissions_mode
        try:
            for name, data in files:
                path = Path(self.path(name))
                if path.parent not in folders:
                    path.parent.mkdir(
                        mode=self.directory_permissions_mode or 0o777, parents=True, exist_ok=True
                    )
                    folders.add(path.parent)
                fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
                written.append(str(path))
                try:
                    os.write(fd, data)  # envelopes are small: one write takes them whole
                    if mode is not None:
                        os.fchmod(fd, mode)  # on the open file: no second lookup of the path
                finally:
                    os.close(fd)
        except BaseException:
            _paths_remove(written)
            raise
        return written

    def sync_written(self, paths: Sequence[str]) -> None:
        """Make files written by `write_new` and their directory entries durable."""
        _sync(paths, self.location)


class DurableS3Storage(S3Storage):
    """An S3 bucket (ENVELOPE_STORAGE_URL=s3://...), shared by every host. A write counts once
    the server confirmed the very bytes: the PUT carries their Content-MD5, which the server
    checks (a mismatch is refused), and the ETag it answers must be that MD5."""

    def _save(self, name: str, content) -> str:
        if hasattr(content, "seek"):
            content.seek(0)
        return self.save_durably([(name, content.read())])[0]

    def save_durably(self, files: Sequence[tuple[str, bytes]]) -> list[str]:
        """PUT the files side by side (S3_PARALLEL_PUTS at a time), each confirmed; all or
        none: the ones written are deleted again when another fails."""
        client = self.connection.meta.client  # boto3 clients are thread-safe; resources not
        names = [clean_name(name) for name, _ in files]
        with ThreadPoolExecutor(max_workers=max(1, min(S3_PARALLEL_PUTS, len(files)))) as pool:
            futures = [
                pool.submit(self._put, client, name, data)
                for name, (_, data) in zip(names, files, strict=True)
            ]
            wait(futures)
        failed = [future.exception() for future in futures if future.exception() is not None]
        if failed:
            # Every one, not only those confirmed: a PUT that failed may have been stored.
            for name in names:
                with suppress(Exception):
                    client.delete_object(Bucket=self.bucket_name, Key=self._key(name))
            raise failed[0]
        return names

    def save_streamed(self, name: str, content: IO[bytes]) -> str:
        """Upload an open file of any size (multipart above S3_PART_SIZE), confirmed by the
        size the server then reports."""
        client = self.connection.meta.client
        key = self._key(name)
        size = content.seek(0, os.SEEK_END)
        content.seek(0)
        client.upload_fileobj(
            content,
            self.bucket_name,
            key,
            ExtraArgs={"ContentType": "application/octet-stream"},
            Config=_S3_TRANSFER,
        )
        stored = client.head_object(Bucket=self.bucket_name, Key=key)["ContentLength"]
        if stored != size:
            with suppress(Exception):
                client.delete_object(Bucket=self.bucket_name, Key=key)
            raise OSError(f"the S3 server holds {stored} bytes of {name}, not {size}")
        return clean_name(name)

    def _key(self, name: str) -> str:
        return self._normalize_name(clean_name(name))

    def _put(self, client: Any, name: str, data: bytes) -> None:
        md5 = hashlib.md5(data, usedforsecurity=False)
        answer = client.put_object(
            Bucket=self.bucket_name,
            Key=self._key(name),
            Body=data,
            ContentMD5=base64.b64encode(md5.digest()).decode(),
            ContentType="application/octet-stream",
        )
        if answer.get("ETag", "").strip('"') != md5.hexdigest():
            raise OSError(f"the S3 server confirmed other bytes for {name} than were sent")


def envelopes_save(storage: Storage, files: Sequence[tuple[str, bytes]]) -> list[str]:
    """Save each (name, data), durable when this returns; the names they were saved as. A
    failure leaves none of them behind, and is StorageUnavailable."""
    try:
        if isinstance(storage, DurableFileSystemStorage | DurableS3Storage):
            return storage.save_durably(files)
        return _save_each(storage, files)
    except (OSError, BotoCoreError, ClientError) as exc:
        logger.error("envelope storage refused %d files: %s", len(files), exc)
        raise StorageUnavailable(
            "the portal could not store the envelopes durably; nothing was stored, send them again"
        ) from exc


def file_save(storage: Storage, name: str, content: IO[bytes]) -> str:
    """Save one file of any size from an open binary file, in constant memory (local disk:
    copied in chunks and fsync'd; S3: a multipart upload), durable when this returns; the
    name it was saved as. A failure is StorageUnavailable."""
    try:
        if isinstance(storage, DurableS3Storage):
            return storage.save_streamed(name, content)
        content.seek(0)
        return storage.save(name, File(content, name=name))
    except (OSError, BotoCoreError, ClientError) as exc:
        logger.error("envelope storage refused %s: %s", name, exc)
        raise StorageUnavailable(
            "the portal could not store the file durably; nothing was stored, try again"
        ) from exc


def _save_each(storage: Storage, files: Sequence[tuple[str, bytes]]) -> list[str]:
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


# Envelopes of an upload handed to a file writer thread at a time, while the upload's next
# ones are checked: the kernel's work of creating them runs beside the checks' Python.
WRITE_CHUNK = 20
_writers: tuple[int, ThreadPoolExecutor] | None = None
_writers_lock = threading.Lock()


def _writer_pool() -> ThreadPoolExecutor:
    """This process's file writer threads (made again in a forked child: threads do not
    survive a fork)."""
    global _writers
    with _writers_lock:
        if _writers is None or _writers[0] != os.getpid():
            _writers = (os.getpid(), ThreadPoolExecutor(2, thread_name_prefix="envelope-files"))
        return _writers[1]


class EnvelopeWriter:
    """The files of one upload, written while the upload is still being checked (local disk:
    WRITE_CHUNK at a time by a writer thread; other storage: all at once in `durable`).
    `durable` answers their names once every file is written and synced, all or none
    (StorageUnavailable); `discard` removes whatever was written, for an upload refused or
    failed before or after. Nothing is durable, or answered stored, before `durable`."""

    def __init__(self, storage: Storage) -> None:
        self._storage = storage
        self._local = isinstance(storage, DurableFileSystemStorage)
        self._files: list[tuple[str, bytes]] = []
        self._chunk: list[tuple[str, bytes]] = []
        self._pending: list[Future[list[str]]] = []
        self._written: list[str] = []
        self._saved: list[str] = []  # names saved by envelopes_save (storage not local)

    def add(self, name: str, data: bytes) -> None:
        self._files.append((name, data))
        if self._local:
            self._chunk.append((name, data))
            if len(self._chunk) >= WRITE_CHUNK:
                self._pending.append(_writer_pool().submit(self._storage.write_new, self._chunk))
                self._chunk = []

    def durable(self) -> list[str]:
        """Every file written and durable; their names, in the order added."""
        if not self._local:
            self._saved = envelopes_save(self._storage, self._files)
            return self._saved
        try:
            if self._chunk:  # the last few (a single envelope's upload: all) in this thread
                self._written.extend(self._storage.write_new(self._chunk))
                self._chunk = []
            failure = self._collect()
            if failure is not None:
                raise failure
            self._storage.sync_written(self._written)
        except OSError as exc:
            self.discard()
            logger.error("envelope storage refused %d files: %s", len(self._files), exc)
            raise StorageUnavailable(
                "the portal could not store the envelopes durably; nothing was stored, send "
                "them again"
            ) from exc
        except BaseException:
            self.discard()
            raise
        return [name for name, _ in self._files]

    def discard(self) -> None:
        """Remove every file of the upload written so far (waiting for those in hand)."""
        self._chunk = []
        self._collect()
        _paths_remove(self._written)
        self._written = []
        storage = self._storage
        for name in self._saved:
            with suppress(OSError):
                storage.delete(name)
        self._saved = []

    def _collect(self) -> BaseException | None:
        """Wait for the writer thread's chunks; the first failure, if one failed (a chunk
        that failed left none of its files)."""
        failure = None
        for future in self._pending:
            try:
                self._written.extend(future.result())
            except BaseException as exc:
                failure = failure or exc
        self._pending = []
        return failure


def _paths_remove(paths: Sequence[str]) -> None:
    for path in paths:
        with suppress(OSError):
            os.remove(path)


def envelope_storage() -> Storage:
    return storages["envelopes"]


def _sync(paths: Sequence[str], location: str) -> None:
    """Make new files and their directory entries durable: a syncfs of the file system that
    holds them (shared with the threads that need one at the same time), or an fsync of each
    file and each of their directories."""
    if not paths:
        return
    if filesystem_sync(location):
        return
    for path in paths:
        fsync_path(path)
    for directory in {os.path.dirname(path) for path in paths}:
        fsync_path(directory)
