"""SM2 (GB/T 32918) on curve sm2p256v1: key pairs, C1C3C2 encryption and SM3 signatures.

Point arithmetic and signatures come from gmssl; randomness, key checks, the KDF and the C3
check are done here, because gmssl draws nonces from `random`, does not check C3 on
decryption and corrupts public keys with `lstrip("04")`.

Formats (DESIGN.md, fixed): private key 64 hex; public key `04||x||y` (130 hex, 128 without
the `04` also accepted); ciphertext hex C1C3C2 with C1 as `x||y` (a leading `04` accepted);
signature r||s (128 hex) over SM3(Z||data) with the default user ID "1234567812345678".
"""

import hmac
import re
import secrets

from gmssl.sm2 import CryptSM2, default_ecc_table

from smcrypto.errors import CryptoError, DecryptionError, InvalidKey
from smcrypto.sm3 import DIGEST_SIZE, sm3_digest

_P = int(default_ecc_table["p"], 16)
_A = int(default_ecc_table["a"], 16)
_B = int(default_ecc_table["b"], 16)
_N = int(default_ecc_table["n"], 16)
_G = default_ecc_table["g"].lower()
_COORDINATE_SIZE = 32
_POINT_SIZE = 2 * _COORDINATE_SIZE
_C2_OFFSET = _POINT_SIZE + DIGEST_SIZE
_HEX = re.compile(r"[0-9a-fA-F]*")


class _GmsslSM2(CryptSM2):
    """gmssl's CryptSM2 in C1C3C2 mode, holding the public key exactly as given (128 hex)."""

    def __init__(self, private_key: str = "", public_key_xy: str = "") -> None:
        super().__init__(private_key=private_key, public_key="", mode=1)
        # set after construction: gmssl's constructor would lstrip("04") it
        self.public_key = public_key_xy


_CURVE = _GmsslSM2()


def generate_keypair() -> tuple[str, str]:
    """Return a new (private key 64 hex, public key `04||x||y` 130 hex)."""
    secret = secrets.randbelow(_N - 2) + 1
    return f"{secret:064x}", "04" + _multiply(secret, _G)


def public_key_from_private(private_key_hex: str) -> str:
    """Return the public key `04||x||y` (130 hex) of a private key."""
    return "04" + _multiply(_parse_private_key(private_key_hex), _G)


def public_key_normalize(public_key_hex: str) -> str:
    """The public key as `04||x||y` lowercase hex (130), checked to be a point on sm2p256v1
    (gmssl does not check); InvalidKey otherwise."""
    return "04" + _parse_public_key(public_key_hex)


def fingerprint(public_key_hex: str) -> str:
    """A short name of a public key for people to compare: the first 8 bytes of SM3 of
    `04||x||y`, as four groups of four hex digits (`1a2b:3c4d:5e6f:7a8b`)."""
    digest = sm3_digest(bytes.fromhex(public_key_normalize(public_key_hex))).hex()[:16]
    return ":".join(digest[i : i + 4] for i in range(0, 16, 4))


def encrypt(public_key_hex: str, data: bytes) -> str:
    """Encrypt data to a public key; return C1C3C2 hex with C1 as x||y (no `04`)."""
    point = _parse_public_key(public_key_hex)
    if not data:
        raise CryptoError("SM2 cannot encrypt an empty message")
    while True:
        ciphertext = _encrypt_with_ephemeral(point, bytes(data), secrets.randbelow(_N - 1) + 1)
        if ciphertext is not None:
            return ciphertext


def decrypt(private_key_hex: str, ciphertext_hex: str) -> bytes:
    """Decrypt C1C3C2 hex (C1 with or without a leading `04`); raise DecryptionError on failure."""
    secret = _parse_private_key(private_key_hex)
    if (
        not isinstance(ciphertext_hex, str)
        or len(ciphertext_hex) % 2
        or not _is_hex(ciphertext_hex)
    ):
        raise DecryptionError("SM2 ciphertext must be a string of hex digit pairs")
    raw = bytes.fromhex(ciphertext_hex)
    candidates = [raw]
    if raw[:1] == b"\x04":
        # x may itself start with 04, so try both readings; only one has C1 on the curve
        candidates.append(raw[1:])
    reasons = []
    for candidate in candidates:
        plaintext, reason = _decrypt_raw(secret, candidate)
        if plaintext is not None:
            return plaintext
        reasons.append(reason)
    # Of two readings, the one with C1 on the curve says why; the other only that it is not.
    reason = next((reason for reason in reasons if reason != _C1_OFF_CURVE), reasons[-1])
    raise DecryptionError(f"SM2 decryption failed: {reason}")


def sign(private_key_hex: str, data: bytes) -> str:
    """Sign data (SM3 with the default user ID); return r||s as 128 hex."""
    secret = _parse_private_key(private_key_hex)
    signer = _GmsslSM2(private_key=f"{secret:064x}", public_key_xy=_multiply(secret, _G))
    while True:
        nonce = secrets.randbelow(_N - 1) + 1
        signature = signer.sign_with_sm3(bytes(data), f"{nonce:064x}")
        if signature is not None:
            return signature


def verify(public_key_hex: str, data: bytes, signature_hex: str) -> bool:
    """Return whether signature_hex (r||s, 128 hex) is a valid signature of data by the key."""
    point = _parse_public_key(public_key_hex)
    if not isinstance(signature_hex, str) or len(signature_hex) != 128:
        return False
    if not _is_hex(signature_hex):
        return False
    r, s = int(signature_hex[:64], 16), int(signature_hex[64:], 16)
    if not (0 < r < _N and 0 < s < _N) or (r + s) % _N == 0:
        return False
    try:
        return bool(_GmsslSM2(public_key_xy=point).verify_with_sm3(signature_hex, bytes(data)))
    except (TypeError, ValueError):
        # gmssl fails this way when the two points of the check sum to infinity: not valid
        return False


def _encrypt_with_ephemeral(point: str, data: bytes, ephemeral: int) -> str | None:
    c1 = _multiply(ephemeral, _G)
    shared = bytes.fromhex(_multiply(ephemeral, point))
    mask = _kdf(shared, len(data))
    if not any(mask):
        return None
    c2 = _xor(data, mask)
    c3 = sm3_digest(shared[:_COORDINATE_SIZE] + data + shared[_COORDINATE_SIZE:])
    return c1 + c3.hex() + c2.hex()


_C1_OFF_CURVE = "C1 is not a point on the SM2 curve"


def _decrypt_raw(secret: int, raw: bytes) -> tuple[bytes | None, str]:
    if len(raw) <= _C2_OFFSET:
        return None, f"ciphertext is {len(raw)} bytes, too short for C1 (64), C3 (32) and data"
    c1, c3, c2 = raw[:_POINT_SIZE], raw[_POINT_SIZE:_C2_OFFSET], raw[_C2_OFFSET:]
    if not _on_curve(c1):
        return None, _C1_OFF_CURVE
    shared = bytes.fromhex(_multiply(secret, c1.hex()))
    mask = _kdf(shared, len(c2))
    if not any(mask):
        return None, "the key derivation produced an all-zero mask"
    plaintext = _xor(c2, mask)
    check = sm3_digest(shared[:_COORDINATE_SIZE] + plaintext + shared[_COORDINATE_SIZE:])
    if not hmac.compare_digest(check, c3):
        return None, "C3 check failed (wrong private key or corrupted ciphertext)"
    return plaintext, ""


def _kdf(shared: bytes, length: int) -> bytes:
    blocks = -(-length // DIGEST_SIZE)
    stream = b"".join(
        sm3_digest(shared + counter.to_bytes(4, "big")) for counter in range(1, blocks + 1)
    )
    return stream[:length]


def _xor(data: bytes, mask: bytes) -> bytes:
    return (int.from_bytes(data, "big") ^ int.from_bytes(mask, "big")).to_bytes(len(data), "big")


def _multiply(scalar: int, point_xy: str) -> str:
    # gmssl's _kg is only right for 1 <= scalar < n and a point on the curve: callers ensure both
    result = _CURVE._kg(scalar, point_xy)
    if result is None:
        raise CryptoError("SM2 point multiplication reached the point at infinity")
    return result


def _on_curve(point: bytes) -> bool:
    x = int.from_bytes(point[:_COORDINATE_SIZE], "big")
    y = int.from_bytes(point[_COORDINATE_SIZE:], "big")
    if x >= _P or y >= _P:
        return False
    return (y * y - (x * x * x + _A * x + _B)) % _P == 0


def _parse_private_key(private_key_hex: str) -> int:
    if not isinstance(private_key_hex, str) or len(private_key_hex) != 64:
        raise InvalidKey("SM2 private key must be 64 hex digits")
    if not _is_hex(private_key_hex):
        raise InvalidKey("SM2 private key must contain only hex digits")
    secret = int(private_key_hex, 16)
    if not 1 <= secret <= _N - 2:
        raise InvalidKey("SM2 private key is out of range [1, n-2]")
    return secret


def _parse_public_key(public_key_hex: str) -> str:
    if not isinstance(public_key_hex, str):
        raise InvalidKey(
            f"SM2 public key must be a hex string, got {type(public_key_hex).__name__}"
        )
    if len(public_key_hex) == 130 and public_key_hex.startswith("04"):
        public_key_hex = public_key_hex[2:]
    if len(public_key_hex) != 128:
        raise InvalidKey("SM2 public key must be 130 hex digits (04||x||y) or 128 (x||y)")
    if not _is_hex(public_key_hex):
        raise InvalidKey("SM2 public key must contain only hex digits")
    if not _on_curve(bytes.fromhex(public_key_hex)):
        raise InvalidKey("SM2 public key is not a point on the SM2 curve")
    return public_key_hex.lower()


def _is_hex(text: str) -> bool:
    return _HEX.fullmatch(text) is not None
