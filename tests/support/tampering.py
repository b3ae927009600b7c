"""A stored envelope changed behind the portal's back, as a disk or an operator could: for
tests of what the integrity check catches."""

from core.redis_client import get_redis
from sharing.cache import _key as cache_key
from sharing.models import Record
from sharing.storage import envelope_storage


def tamper(record: Record) -> None:
    """Flip one byte of the stored envelope (durable copy), and drop the cached one."""
    get_redis().delete(cache_key(record.id))
    path = envelope_storage().path(record.storage_name)
    with open(path, "r+b") as handle:
        handle.seek(40)
        byte = handle.read(1)
        handle.seek(40)
        handle.write(bytes([byte[0] ^ 0x01]))
