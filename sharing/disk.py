"""The disks this host's portal writes uploads to (the local envelope storage, the SQLite
database): an upload or an export is refused before one of them fills up, and the operator is
alerted well before that.

A full disk fails everything at once, at random places: SQLite can neither commit nor
checkpoint, envelopes are not written, sessions and logs stop. Below STORAGE_MIN_FREE_BYTES an
upload is answered 503 `storage_unavailable` (Retry-After 60) and nothing of it is written: the
robot keeps it in its spool and sends it again. Below STORAGE_LOW_FREE_BYTES the operator gets
an alert (`disk-low`, one per folder), checked by the beat every STORAGE_CHECK_INTERVAL seconds
and resolved once there is room again. An S3 bucket or a PostgreSQL server is not this host's
disk and is not checked here.
"""

import logging
import threading
import time
from pathlib import Path

from django.conf import settings
from django.core.files.storage import FileSystemStorage
from django.db import DEFAULT_DB_ALIAS, connections

from chainworker.services import operator_alert_raise, operator_alert_resolve
from core.files import filesystem_free
from sharing.errors import StorageFull
from sharing.storage import envelope_storage

logger = logging.getLogger(__name__)

DISK_LOW_ALERT = "disk-low"
# An operator alert's subject holds at most this many characters (OperatorAlert.subject).
_SUBJECT_LENGTH = 100
# Refused uploads are logged at most once this many seconds per process (each is a 503).
REFUSAL_LOG_INTERVAL = 60.0
_refusals_logged = {"at": float("-inf")}
_refusals_lock = threading.Lock()


def portal_disks() -> list[Path]:
    """The folders on this host's disks that uploads are written to: the envelope storage's
    when it is the local disk, and the SQLite database's."""
    folders = []
    storage = envelope_storage()
    if isinstance(storage, FileSystemStorage):
        folders.append(Path(storage.location).absolute())
    connection = connections[DEFAULT_DB_ALIAS]
    name = str(connection.settings_dict["NAME"])
    if connection.vendor == "sqlite" and name != ":memory:" and not name.startswith("file:"):
        folders.append(Path(name).absolute().parent)
    return folders


def disk_room_check(needed: int) -> None:
    """StorageFull when writing `needed` more bytes would leave less than
    STORAGE_MIN_FREE_BYTES on a disk uploads are written to. A disk whose room cannot be
    read is not held against the upload."""
    floor = settings.STORAGE_MIN_FREE_BYTES
    if floor <= 0:
        return
    for folder in portal_disks():
        try:
            free = filesystem_free(folder)
        except OSError:
            continue
        if free - needed < floor:
            _refusal_log(folder, free)
            raise StorageFull(
                "the portal's disk is nearly full, so nothing was stored: try again later "
                "(the operator is alerted)"
            )


def portal_disks_free() -> dict[Path, int]:
    """The free bytes of each folder of portal_disks() whose room can be read (the watch
    below, and /metrics: portal/scrape.py)."""
    free_of: dict[Path, int] = {}
    for folder in portal_disks():
        try:
            free_of[folder] = filesystem_free(folder)
        except OSError as exc:
            logger.warning("the free space of %s could not be read: %s", folder, exc)
    return free_of


def disk_space_watch() -> dict[str, int]:
    """An operator alert for each folder of portal_disks() with less than
    STORAGE_LOW_FREE_BYTES free, and the alerts of those with room again resolved; the free
    bytes of each folder read."""
    free_of: dict[str, int] = {}
    for folder, free in portal_disks_free().items():
        free_of[str(folder)] = free
        subject = _subject(folder)
        if free < settings.STORAGE_LOW_FREE_BYTES:
            operator_alert_raise(
                kind=DISK_LOW_ALERT,
                subject=subject,
                detail={
                    "folder": str(folder),
                    "free_bytes": free,
                    "alert_below_bytes": settings.STORAGE_LOW_FREE_BYTES,
                    "uploads_refused_below_bytes": settings.STORAGE_MIN_FREE_BYTES,
                },
            )
        else:
            operator_alert_resolve(kind=DISK_LOW_ALERT, subject=subject)
    return free_of


def _subject(folder: Path) -> str:
    """The folder as an alert's subject: its end, where a path is too long for one."""
    text = str(folder)
    return text if len(text) <= _SUBJECT_LENGTH else "…" + text[-(_SUBJECT_LENGTH - 1) :]


def _refusal_log(folder: Path, free: int) -> None:
    with _refusals_lock:
        now = time.monotonic()
        if now - _refusals_logged["at"] < REFUSAL_LOG_INTERVAL:
            return
        _refusals_logged["at"] = now
    logger.error(
        "uploads refused: %s has %d bytes free, below STORAGE_MIN_FREE_BYTES (%d)",
        folder,
        free,
        settings.STORAGE_MIN_FREE_BYTES,
    )
