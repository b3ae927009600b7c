"""SM2/SM3/SM4 and the record envelope: pure functions, no Django, so robots can use them.

Open an envelope with `smcrypto.envelope.open(key, data)`.
"""

from smcrypto import envelope, sm2, sm3, sm4
from smcrypto.envelope import EnvelopeInfo, digest, key_commitment, key_id, read_header, seal
from smcrypto.errors import (
    AuthenticationFailed,
    CryptoError,
    DecryptionError,
    InvalidData,
    InvalidKey,
    MalformedEnvelope,
    UnsupportedEnvelope,
    WrongKey,
)

__all__ = [
    "AuthenticationFailed",
    "CryptoError",
    "DecryptionError",
    "EnvelopeInfo",
    "InvalidData",
    "InvalidKey",
    "MalformedEnvelope",
    "UnsupportedEnvelope",
    "WrongKey",
    "digest",
    "envelope",
    "key_commitment",
    "key_id",
    "read_header",
    "seal",
    "sm2",
    "sm3",
    "sm4",
]
