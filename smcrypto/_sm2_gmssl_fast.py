"""SM2 in GmSSL's C through PyPI `gmssl-fast` (a Rust extension with GmSSL 3 linked in, abi3
wheels for Linux x86_64 and aarch64): smcrypto.sm2's backend where Tongsuo is not installed
and this is, once it has reproduced GB/T 32918's examples at import.

The agent's and the verifier's extras install it on Linux aarch64 only, where Tongsuo has no
wheel (0.1.0, its only release, built from a patched fork of gmssl-rs: pinned, and checked at
every import); on x86_64 Tongsuo is first. Its limits, met here: it encrypts and decrypts at
most 255 bytes of plaintext (GmSSL's fixed buffer), so longer messages take the pure-Python
backend; it cannot give a private key's public key, so that too is the pure-Python backend's
(once per key); every failed call (a signature that
does not hold, a C3 mismatch) makes GmSSL print its call trace to stderr; it holds the GIL.
Whether GmSSL's scalar multiplication is constant-time neither package says: treat it as not.
Measured on this project's 2-core machine (idle): sign 0.78 ms, verify 1.43 ms, encrypt 1.47 ms,
decrypt 0.69 ms (Tongsuo: 0.27, 0.24, 0.48, 0.25).
"""

from functools import lru_cache

# named imports: a release without them is an ImportError, so the next backend is chosen
from gmssl_fast._core import GmsslError, GmsslValueError, Sm2KeyHandle

from smcrypto import _sm2_gmssl

NAME = "gmssl-fast"
RELEASES_GIL = False
_MAX_PLAINTEXT = 255
# what its calls raise when GmSSL refuses (GmsslValueError is a ValueError, not a GmsslError)
_REFUSED = (GmsslError, GmsslValueError)

# GB/T 32918.5's example key, its signature of "message digest" (GB/T 32918.2) and its
# encryption of "encryption standard" (GB/T 32918.4): checked at import.
_KAT_PRIVATE = "3945208f7b2144b13f36e38ac6d39f95889393692860b51a42fb81ef4df7c5b8"
_KAT_PUBLIC = (
    "09f9df311e5421a150dd7d161e4bc5c672179fad1833fc076bb08ff356f35020"
    "ccea490ce26775a52dc6ea718cc1aa600aed05fbf35e084a6632f6072da9ad13"
)
_KAT_SIGNATURE = (
    "f5a03b0648d2c4630eeac513e1bb81a15944da3827d5b74143ac7eaceee720b3"
    "b1b6aa29df212fd8763182bc0d421ca1bb9038fd1f7f42d4840b69c485bbc1aa"
)
_KAT_CIPHERTEXT = (
    "04ebfc718e8d1798620432268e77feb6415e2ede0e073c0f4f640ecd2e149a73"
    "e858f9d81e5430a57b36daab8f950a3c64e6ee6a63094d99283aff767e124df0"
    "59983c18f809e262923c53aec295d30383b54e39d609d160afcb1908d0bd8766"
    "21886ca989ca9c7d58087307ca93092d651efa"
)


def public_key_xy(secret: int) -> str:
    return _sm2_gmssl.public_key_xy(secret)


def sign(secret: int, data: bytes) -> tuple[int, int]:
    raw = _private(secret).sign(data)
    return int.from_bytes(raw[:32], "big"), int.from_bytes(raw[32:], "big")


def verify(public_key_xy: str, data: bytes, r: int, s: int) -> bool:
    signature = r.to_bytes(32, "big") + s.to_bytes(32, "big")
    try:
        return _public(public_key_xy).verify(data, signature) is True
    except _REFUSED:
        return False


def encrypt(public_key_xy: str, data: bytes) -> bytes:
    if len(data) > _MAX_PLAINTEXT:
        return _sm2_gmssl.encrypt(public_key_xy, data)
    return _public(public_key_xy).encrypt(data)


def decrypt(secret: int, c1: bytes, c3: bytes, c2: bytes) -> bytes | None:
    if len(c2) > _MAX_PLAINTEXT:
        return _sm2_gmssl.decrypt(secret, c1, c3, c2)
    try:
        plaintext = _private(secret).decrypt(c1 + c3 + c2)
    except _REFUSED:
        return None
    # it also tries the ciphertext without a leading 04; only the reading given may answer
    return plaintext if len(plaintext) == len(c2) else None


@lru_cache(maxsize=64)
def _private(secret: int) -> Sm2KeyHandle:
    # GmSSL derives the public key in C (and checks it) once per handle
    return Sm2KeyHandle(f"{secret:064x}", None)


@lru_cache(maxsize=256)
def _public(public_key_xy: str) -> Sm2KeyHandle:
    return Sm2KeyHandle(None, "04" + public_key_xy)


def _self_check() -> None:
    """ImportError unless this build verifies the standard's signature and decrypts the
    standard's ciphertext (C1 as given, its x starting with 04). Nothing here fails when the
    build is right: a refusal would print GmSSL's trace at every import. Any error of another
    release's API counts as failing: the next backend is chosen."""
    try:
        holds = _public(_KAT_PUBLIC).verify(b"message digest", bytes.fromhex(_KAT_SIGNATURE))
        plaintext = Sm2KeyHandle(_KAT_PRIVATE, "04" + _KAT_PUBLIC).decrypt(
            bytes.fromhex(_KAT_CIPHERTEXT)
        )
    except Exception as exc:
        raise ImportError(f"gmssl-fast failed GB/T 32918's examples: {exc!r}") from None
    if holds is not True or plaintext != b"encryption standard":
        raise ImportError("gmssl-fast failed GB/T 32918's examples")


_self_check()
