"""SM3 hash (GB/T 32905) through cryptography/OpenSSL."""

from cryptography.hazmat.primitives import hashes

DIGEST_SIZE = 32


def sm3_digest(data: bytes) -> bytes:
    """Return the 32-byte SM3 digest of data."""
    hasher = hashes.Hash(hashes.SM3())
    hasher.update(data)
    return hasher.finalize()


def sm3_hex(data: bytes) -> str:
    """Return the SM3 digest of data as 64 lowercase hex characters."""
    return sm3_digest(data).hex()


def sm3_hasher() -> hashes.Hash:
    """An SM3 hash fed piece by piece (`update`, then `finalize` for the 32 bytes): for files
    hashed as they are written, in constant memory."""
    return hashes.Hash(hashes.SM3())
