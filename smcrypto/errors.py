"""Exceptions raised by smcrypto: every one is a CryptoError (and so a ValueError)."""


class CryptoError(ValueError):
    """Base of everything smcrypto raises for bad keys, bytes or signatures."""


class InvalidKey(CryptoError):
    """A key, nonce or IV has the wrong type or length, or an SM2 key is not valid."""


class InvalidData(CryptoError):
    """A plaintext, ciphertext or associated data is not bytes."""


class MalformedEnvelope(CryptoError):
    """The bytes are not a well-formed envelope, or a header is not acceptable."""


class UnsupportedEnvelope(CryptoError):
    """The envelope has a version or algorithm this code does not know."""


class WrongKey(CryptoError):
    """The envelope was sealed under a different key than the one given."""


class AuthenticationFailed(CryptoError):
    """The SM4-GCM tag does not match: the data or its header was changed."""


class DecryptionError(CryptoError):
    """SM2 or SM4-CBC decryption failed (wrong key, corrupted data or bad padding)."""


class SignatureInvalid(CryptoError):
    """A record's robot signature does not hold (DESIGN.md "Provenance"); `reason` names the
    check that failed, one of the subclasses' reasons."""

    reason = "invalid"


class SignatureMissing(SignatureInvalid):
    """The header has no `signer` or no `sig`: the record is unsigned."""

    reason = "missing"


class SignatureMalformed(SignatureInvalid):
    """`signer` or `sig` is not lowercase hex of its length, the public key is not an SM2
    point, or the header is not plain JSON."""

    reason = "malformed"


class SignerMismatch(SignatureInvalid):
    """`signer` is not the key hash of the public key given."""

    reason = "signer_mismatch"


class BadSignature(SignatureInvalid):
    """The signature does not verify over the header and plaintext with the key given."""

    reason = "bad_signature"
