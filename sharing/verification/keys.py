"""The SM4 keys records are sealed under, unwrapped from the KEK once per key for one read, one
check run or one export (`RecordKeys`), never kept beyond it."""

from collections.abc import Sequence
from contextlib import suppress

from accounts.models import OwnerKey
from accounts.selectors import owner_key_by_id, owner_key_bytes
from sharing.models import Record
from smcrypto.envelope import OpeningKey


def record_key(record: Record) -> bytes:
    """The SM4 key the record was sealed under."""
    key = owner_key_by_id(record.owner, record.key_id)
    if key is None:
        raise OwnerKey.DoesNotExist(f"no key {record.key_id} of the record's owner")
    return owner_key_bytes(key)


class RecordKeys:
    """The SM4 keys of records, unwrapped once per (owner, key id) for a read or an export."""

    def __init__(self) -> None:
        self._keys: dict[tuple[int, str], bytes] = {}
        self._opening: dict[tuple[int, str], OpeningKey] = {}

    def of(self, record: Record) -> bytes:
        wanted = (record.owner_id, record.key_id)
        if wanted not in self._keys:
            self._keys[wanted] = record_key(record)
        return self._keys[wanted]

    def opening(self, record: Record) -> OpeningKey:
        """The record's key, to open envelopes with (its key id and cipher made once)."""
        wanted = (record.owner_id, record.key_id)
        if wanted not in self._opening:
            self._opening[wanted] = OpeningKey(self.of(record))
        return self._opening[wanted]

    def of_owner_key(self, key: OwnerKey) -> bytes:
        """An owner's key as read (the viewer's current key, to re-seal for them): the bytes
        already unwrapped for a record sealed under it, else unwrapped now."""
        wanted = (key.owner_id, key.key_id)
        if wanted not in self._keys:
            self._keys[wanted] = owner_key_bytes(key)
        return self._keys[wanted]

    def warm(self, records: Sequence[Record]) -> None:
        """Unwrap the records' keys now; one that fails is reported where a record that may
        be shown is opened (the check's verdict comes first)."""
        for record in records:
            with suppress(OwnerKey.DoesNotExist):
                self.of(record)
