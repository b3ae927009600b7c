"""SM2 in pure Python: smcrypto.sm2's fallback, which installs wherever Python does (PyPI
`gmssl`, with `pycryptodomex`), Linux aarch64 robots and auditors included.

gmssl provides the point multiplication (`CryptSM2._kg`, double-and-add on Jacobian
coordinates); the rest is done here, because gmssl's own calls cannot be used as they are:
its nonces and ephemeral keys come from `random.choice` (Mersenne Twister, predictable: a
signature nonce an observer can predict gives away the private key), its decryption computes
C3 but never compares it, its verification reads a Jacobian x as affine when sG = tQ and fails
on a sum at infinity, and it strips leading "0" and "4" digits off a public key's x. So here:
nonces and ephemeral keys from `secrets` in [1, n-1], Z and e with the project's SM3, the
signature equations of GB/T 32918.2, a point sum that handles doubling and infinity, and the
KDF and the C3 comparison of GB/T 32918.4.

Not constant-time: gmssl's ladder branches on each bit of the scalar and Python's integers
take time by their values. See smcrypto.sm2 for where that matters. Measured on this project's
2-core machine (idle): sign 3.4 ms, verify 6.6 ms, encrypt 6.9 ms, decrypt 3.4 ms (Tongsuo:
0.27, 0.24, 0.48, 0.25); it holds the GIL (verify_many checks in the caller's thread).
"""

import hmac
import secrets
from functools import lru_cache

from gmssl.sm2 import CryptSM2

from smcrypto._sm2_curve import G_X, G_Y, N, P, digest_e, kdf, xor
from smcrypto.sm3 import sm3_digest

NAME = "gmssl"
RELEASES_GIL = False
_G = f"{G_X:064x}{G_Y:064x}"
# Only its point arithmetic is used: no key is set on it, and it keeps no state between calls.
_CURVE = CryptSM2(private_key="", public_key="", mode=1)


def public_key_xy(secret: int) -> str:
    return _public_key_of(secret)


def sign(secret: int, data: bytes, *, nonce: int | None = None) -> tuple[int, int]:
    """GB/T 32918.2 6.1 with a nonce from `secrets` (`nonce` is for the standard's example)."""
    e = digest_e(_public_key_of(secret), data)
    inverse = pow(1 + secret, -1, N)
    while True:
        k = nonce if nonce is not None else secrets.randbelow(N - 1) + 1
        x1 = int(_CURVE._kg(k, _G)[:64], 16)
        r = (e + x1) % N
        if r == 0 or r + k == N:
            nonce = None
            continue
        s = inverse * (k - r * secret) % N
        if s:
            return r, s
        nonce = None


def verify(public_key_xy: str, data: bytes, r: int, s: int) -> bool:
    """GB/T 32918.2 7.1 (r, s already in [1, n-1] with r + s not n)."""
    t = (r + s) % N
    total = _point_add(_point(_CURVE._kg(s, _G)), _point(_CURVE._kg(t, public_key_xy)))
    if total is None:
        return False
    return (digest_e(public_key_xy, data) + total[0]) % N == r


def encrypt(public_key_xy: str, data: bytes, *, ephemeral: int | None = None) -> bytes:
    """GB/T 32918.4 6.1: C1 (x||y) || C3 || C2, the ephemeral k from `secrets`; a key stream
    of zeros starts over with a new k (smcrypto.sm2 also checks for it, for every backend)."""
    while True:
        k = ephemeral if ephemeral is not None else secrets.randbelow(N - 1) + 1
        ephemeral = None
        c1 = bytes.fromhex(_CURVE._kg(k, _G))
        shared = bytes.fromhex(_CURVE._kg(k, public_key_xy))
        stream = kdf(shared, len(data))
        if any(stream):
            c3 = sm3_digest(shared[:32] + data + shared[32:])
            return c1 + c3 + xor(data, stream)


def decrypt(secret: int, c1: bytes, c3: bytes, c2: bytes) -> bytes | None:
    """GB/T 32918.4 7.1 (C1 already on the curve): None if the key stream is all zeros or C3
    does not match (a wrong key or a changed ciphertext)."""
    shared = bytes.fromhex(_CURVE._kg(secret, c1.hex()))
    stream = kdf(shared, len(c2))
    if not any(stream):
        return None
    plaintext = xor(c2, stream)
    if not hmac.compare_digest(sm3_digest(shared[:32] + plaintext + shared[32:]), c3):
        return None
    return plaintext


@lru_cache(maxsize=64)
def _public_key_of(secret: int) -> str:
    # cached: a scalar multiplication, and a robot signs with one key
    return _CURVE._kg(secret, _G)


def _point(xy: str | None) -> tuple[int, int] | None:
    return None if xy is None else (int(xy[:64], 16), int(xy[64:], 16))


def _point_add(
    first: tuple[int, int] | None, second: tuple[int, int] | None
) -> tuple[int, int] | None:
    """Affine sum on the curve, None standing for the point at infinity."""
    if first is None or second is None:
        return first if second is None else second
    (x1, y1), (x2, y2) = first, second
    if x1 == x2:
        if (y1 + y2) % P == 0:
            return None
        slope = (3 * x1 * x1 - 3) * pow(2 * y1, -1, P) % P  # a = -3 on sm2p256v1
    else:
        slope = (y2 - y1) * pow(x2 - x1, -1, P) % P
    x3 = (slope * slope - x1 - x2) % P
    return x3, (slope * (x1 - x3) - y1) % P
