"""An export's files streamed to its requester, decrypted as read (smcrypto/stream.py), only
while the export is ready and theirs to have: nothing is streamed otherwise."""

import uuid
from collections.abc import Iterator
from dataclasses import dataclass

from django.utils import timezone

from accounts.keywrap import UnwrapFailed, unwrap
from accounts.models import Owner
from sharing.errors import ExportExpired, ExportNotFound, ExportNotReady, ExportWithdrawn
from sharing.exports.files import export_file_stem, export_key_purpose
from sharing.exports.withdraw import export_withdrawn_if_lost
from sharing.models import Export
from sharing.selectors.exports import export_of
from sharing.storage import envelope_storage
from smcrypto.stream import sealed_open


@dataclass(frozen=True)
class ExportFile:
    """One of an export's files, to stream to its requester: `chunks()` decrypts it as read."""

    name: str
    filename: str
    size: int
    key: bytes

    def chunks(self) -> Iterator[bytes]:
        with envelope_storage().open(self.name, "rb") as sealed:
            yield from sealed_open(sealed, self.key)


def export_download(*, requester: Owner, export_id: uuid.UUID | str, part: str) -> ExportFile:
    """An export's MCAP file (`part` "mcap") or proof bundle ("bundle"), for its requester
    only, while they may view every record in it; ExportNotFound, ExportNotReady,
    ExportExpired or ExportWithdrawn (nothing is streamed then)."""
    export = export_current(requester=requester, export_id=export_id)
    if export.status == Export.Status.WITHDRAWN:
        raise ExportWithdrawn(f"this export is {export.error}; its files are removed")
    if export.status == Export.Status.EXPIRED or export.expires_at <= timezone.now():
        raise ExportExpired("this export has expired and its files are removed; export again")
    if export.status != Export.Status.DONE:
        raise ExportNotReady("this export is not ready yet")
    try:
        key = unwrap(bytes(export.key_wrapped), purpose=export_key_purpose(export.pk))
    except UnwrapFailed:
        raise ExportWithdrawn("this export's key is gone; export again") from None
    stem = export_file_stem(export)
    if part == "mcap":
        return ExportFile(export.mcap_name, f"{stem}.mcap", export.mcap_size, key)
    return ExportFile(export.bundle_name, f"{stem}.proofs.json", export.bundle_size, key)


def export_current(*, requester: Owner, export_id: uuid.UUID | str) -> Export:
    """The requester's export as it stands now: a ready one whose records they may no longer
    all view is withdrawn first. ExportNotFound if it is not theirs."""
    export = export_of(requester, export_id)
    if export is None:
        raise ExportNotFound("no such export of yours")
    if export.status == Export.Status.DONE and export_withdrawn_if_lost(export) is not None:
        export.refresh_from_db()
    return export
