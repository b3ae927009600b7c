"""Where an export's files live and under which key: the storage prefix, the files' names as
downloaded, the purpose their key is wrapped for (accounts/keywrap.py), and their removal (the
key first, so that a copy of the files opens no more)."""

import uuid

from sharing.models import Export, ExportRecord
from sharing.storage import envelope_storage

EXPORT_STORAGE_PREFIX = "exports"


def export_file_stem(export: Export) -> str:
    """The files' names as downloaded: `<stem>.mcap` and `<stem>.proofs.json`."""
    return f"authros-export-{str(export.pk)[:8]}"


def export_key_purpose(export_id: uuid.UUID | str) -> str:
    return f"export-key:{export_id}"


def export_files_remove(export: Export, *, status: str, reason: str | None) -> None:
    """The export's key first (a copy of its files, a backup, opens no more), then its files
    and its list of records; `reason`, if any, is shown as why."""
    said = {} if reason is None else {"error": reason}
    Export.objects.filter(pk=export.pk).update(status=status, key_wrapped=b"", **said)
    storage = envelope_storage()
    for name in (export.mcap_name, export.bundle_name):
        if name:
            storage.delete(name)
    ExportRecord.objects.filter(export=export).delete()
