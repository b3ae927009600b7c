"""A stored envelope changed behind the portal's back, as a disk or an operator could, and a
record written behind it as whoever holds the KEK and the database could: for tests of what
the integrity check catches."""

import uuid
from datetime import datetime

from core.redis_client import get_redis
from sharing.cache import _key as cache_key
from sharing.models import Record
from sharing.services.anchoring import records_anchor
from sharing.storage import envelope_storage, envelopes_save
from smcrypto import envelope, sm3


def tamper(record: Record) -> None:
    """Flip one byte of the stored envelope (durable copy), and drop the cached one."""
    get_redis().delete(cache_key(record.id))
    path = envelope_storage().path(record.storage_name)
    with open(path, "r+b") as handle:
        handle.seek(40)
        byte = handle.read(1)
        handle.seek(40)
        handle.write(bytes([byte[0] ^ 0x01]))


def stored_behind_the_portal(setup, data: bytes, capture, **row: object) -> Record:
    """What the KEK and the database allow: the envelope stored and its row written as an
    upload would write them, none of the upload's checks run, then anchored by the portal
    from the owner's account as any pending record is."""
    header = envelope.read_header(data).header
    record_id = uuid.uuid4()
    (name,) = envelopes_save(envelope_storage(), [(f"{setup.owner.pk}/{record_id}.env", data)])
    record = Record.objects.create(
        id=record_id,
        owner=setup.owner,
        robot=setup.robot,
        topic=header["topic"],
        data_type=header["type"],
        seq=header["seq"],
        captured_at=datetime.fromisoformat(header["time"].replace("Z", "+00:00")),
        key_id=envelope.key_id(setup.key).hex(),
        digest=sm3.sm3_hex(data),
        size=len(data),
        storage_name=name,
        **row,
    )
    with capture(execute=True):
        records_anchor(owner_id=setup.owner.pk)
    record.refresh_from_db()
    assert record.status == Record.Status.ANCHORED
    return record
