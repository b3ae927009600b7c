"""SM2/SM3/SM4 and the record envelope: pure functions, no Django, so robots can use them.

Open an envelope with `smcrypto.envelope.open(key, data)`; check a robot's signature on it
with `smcrypto.provenance.verify_header(public_key, header, plaintext)`.
"""

from smcrypto import envelope, provenance, sm2, sm3, sm4
from smcrypto.envelope import EnvelopeInfo, digest, key_commitment, key_id, read_header, seal
from smcrypto.errors import (
    AuthenticationFailed,
    BadSignature,
    CryptoError,
    DecryptionError,
    InvalidData,
    InvalidKey,
    MalformedEnvelope,
    SignatureInvalid,
    SignatureMalformed,
    SignatureMissing,
    SignerMismatch,
    UnsupportedEnvelope,
    WrongKey,
)

__all__ = [
    "AuthenticationFailed",
    "BadSignature",
    "CryptoError",
    "DecryptionError",
    "EnvelopeInfo",
    "InvalidData",
    "InvalidKey",
    "MalformedEnvelope",
    "SignatureInvalid",
    "SignatureMalformed",
    "SignatureMissing",
    "SignerMismatch",
    "UnsupportedEnvelope",
    "WrongKey",
    "digest",
    "envelope",
    "key_commitment",
    "key_id",
    "provenance",
    "read_header",
    "seal",
    "sm2",
    "sm3",
    "sm4",
]
