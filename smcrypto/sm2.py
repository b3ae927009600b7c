"""SM2 (GB/T 32918) on curve sm2p256v1: key pairs, C1C3C2 encryption and SM3 signatures.

Formats (DESIGN.md, fixed): private key 64 hex; public key `04||x||y` (130 hex, 128 without
the `04` also accepted); ciphertext hex C1C3C2 with C1 as `x||y` (a leading `04` accepted);
signature r||s (128 hex) over SM3(Z||data) with the default user ID "1234567812345678"
(GB/T 32918.2, as gmssl `sign_with_sm3` and Tongsuo's `ECDSA(SM3)` on an SM2 key compute it).

The arithmetic is a backend's, chosen when this module is imported; `BACKEND` names it:

- `tongsuo` (smcrypto._sm2_tongsuo): Tongsuo 8.3's C through `tongsuopy`, wherever it imports.
  tongsuopy has wheels for Linux x86_64 and macOS only (no source to build), so the locked sets
  install it there: the portal's, most workstations' and x86_64 robots' backend.
- `gmssl-fast` (smcrypto._sm2_gmssl_fast): GmSSL's C, if that package is installed and
  reproduces GB/T 32918's examples at import. It has Linux x86_64 and aarch64 wheels; the
  agent's and the verifier's locked sets install it on Linux aarch64 (Jetson, Raspberry Pi),
  the suite's on every Linux, so that it is tested against the others.
- `gmssl` (smcrypto._sm2_gmssl): pure Python on gmssl's point arithmetic, everywhere. With one
  signature per upload batch (provenance v2) its few milliseconds a signature are a robot's
  whole cost per batch, and a check verifies each batch once.

AUTHROS_SM2_BACKEND=tongsuo|gmssl-fast|gmssl forces one (for tests, and for operators): a
forced backend that does not import is an ImportError here, never a quiet fallback. Every
backend takes and gives the same hex formats and raises the same errors: the key, input and
format checks, C1's curve check and the reasons a decryption fails are all done here, and
tests/smcrypto/test_sm2.py runs every test against each backend present and each against the
others both ways.

Constant time. Tongsuo's multiplications by a secret scalar use OpenSSL's constant-time ladder.
gmssl's do not: a double-and-add that branches on every bit of the scalar, on Python integers
whose operations take time by their values. gmssl-fast's package promises nothing either way,
so take it as not constant-time too. That matters where a secret scalar is multiplied and
someone can time it, many times: signing on a robot (the nonce k of each batch signature;
timing leaks of nonces, gathered over many signatures, give away the private key) and, far
less often, the robot's decryption of its pairing token and owner keys with its pairing key,
and the public key derived from that key at start. One signature per batch rather than per
record leaves about a hundred times fewer signatures to time, not none: a robot on which
hostile code may run beside the agent should use Tongsuo (x86_64) or keep that code off the
machine. Verification handles only public data (the key, the message, the signature), so the
portal's checks and `authros-verify` lose nothing to the backend's timing, only speed.
"""

import importlib
import os
import re
import secrets
import threading
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from types import ModuleType

from smcrypto._sm2_curve import C2_OFFSET as _C2_OFFSET
from smcrypto._sm2_curve import POINT_SIZE as _POINT_SIZE
from smcrypto._sm2_curve import N as _N
from smcrypto._sm2_curve import on_curve as _on_curve
from smcrypto.errors import CryptoError, DecryptionError, InvalidKey
from smcrypto.sm3 import sm3_digest

# Chosen in this order; the environment variable names one of them.
BACKENDS = ("tongsuo", "gmssl-fast", "gmssl")
BACKEND_VARIABLE = "AUTHROS_SM2_BACKEND"
_MODULES = {
    "tongsuo": "smcrypto._sm2_tongsuo",
    "gmssl-fast": "smcrypto._sm2_gmssl_fast",
    "gmssl": "smcrypto._sm2_gmssl",
}
_HEX = re.compile(r"[0-9a-fA-F]*")
_C1_OFF_CURVE = "C1 is not a point on the SM2 curve"
_C3_MISMATCH = "C3 check failed (wrong private key or corrupted ciphertext)"


def backend_load(name: str) -> ModuleType:
    """The backend module of that name; ImportError if it is not installed here (or, for
    gmssl-fast, fails the standard's examples) or the name is not one of BACKENDS."""
    if name not in _MODULES:
        raise ImportError(f"{BACKEND_VARIABLE} must be one of {', '.join(BACKENDS)}, not {name!r}")
    return importlib.import_module(_MODULES[name])


def _backend_choose() -> ModuleType:
    forced = os.environ.get(BACKEND_VARIABLE, "").strip()
    if forced:
        try:
            return backend_load(forced)
        except ImportError as exc:
            raise ImportError(f"{BACKEND_VARIABLE}={forced}: {exc}") from exc
    reasons = []
    for name in BACKENDS:
        try:
            return backend_load(name)
        except ImportError as exc:
            reasons.append(f"{name}: {exc}")
    raise ImportError("no SM2 backend imports here (" + "; ".join(reasons) + ")")


_backend = _backend_choose()
BACKEND: str = _backend.NAME


def generate_keypair() -> tuple[str, str]:
    """Return a new (private key 64 hex, public key `04||x||y` 130 hex)."""
    secret = secrets.randbelow(_N - 2) + 1
    private_key_hex = f"{secret:064x}"
    return private_key_hex, public_key_from_private(private_key_hex)


def public_key_from_private(private_key_hex: str) -> str:
    """Return the public key `04||x||y` (130 hex) of a private key."""
    return "04" + _backend.public_key_xy(_parse_private_key(private_key_hex))


def public_key_normalize(public_key_hex: str) -> str:
    """The public key as `04||x||y` lowercase hex (130), checked to be a point on sm2p256v1;
    InvalidKey otherwise."""
    return "04" + _parse_public_key(public_key_hex)


def fingerprint(public_key_hex: str) -> str:
    """A short name of a public key for people to compare: the first 8 bytes of SM3 of
    `04||x||y`, as four groups of four hex digits (`1a2b:3c4d:5e6f:7a8b`)."""
    digest = sm3_digest(bytes.fromhex(public_key_normalize(public_key_hex))).hex()[:16]
    return ":".join(digest[i : i + 4] for i in range(0, 16, 4))


def encrypt(public_key_hex: str, data: bytes) -> str:
    """Encrypt data to a public key; return C1C3C2 hex with C1 as x||y (no `04`)."""
    public_key_xy = _parse_public_key(public_key_hex)
    if not data:
        raise CryptoError("SM2 cannot encrypt an empty message")
    data = bytes(data)
    while True:
        raw = _backend.encrypt(public_key_xy, data)
        # GB/T 32918.4 A5: a key stream t of zeros (C2 = M ^ t equal to M) starts over with a
        # new k. Tongsuo does not, and decryptors that follow the standard (gmssl) refuse such
        # a ciphertext: one in 256 of one-byte messages.
        if raw[_C2_OFFSET:] != data:
            return raw.hex()


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
    r, s = _backend.sign(_parse_private_key(private_key_hex), bytes(data))
    return f"{r:064x}{s:064x}"


def verify(public_key_hex: str, data: bytes, signature_hex: str) -> bool:
    """Return whether signature_hex (r||s, 128 hex) is a valid signature of data by the key."""
    public_key_xy = _parse_public_key(public_key_hex)
    if not isinstance(signature_hex, str) or len(signature_hex) != 128:
        return False
    if not _is_hex(signature_hex):
        return False
    r, s = int(signature_hex[:64], 16), int(signature_hex[64:], 16)
    if not (0 < r < _N and 0 < s < _N) or (r + s) % _N == 0:
        return False
    return _backend.verify(public_key_xy, bytes(data), r, s)


# verify_many's threads: Tongsuo's verification runs without the GIL, so a batch of signatures
# is checked on every core of the process (the other backends hold it: one thread). The pool is
# made per process (a forked worker does not inherit its parent's threads).
_POOL_LOCK = threading.Lock()
_pool: tuple[int, ThreadPoolExecutor] | None = None
# Below this many signatures the batch is checked in the caller's thread.
_POOL_FROM = 8


def verify_many(claims: Sequence[tuple[str, bytes, str]]) -> list[bool]:
    """verify() of each (public key, data, signature), in order, on every core: one answer per
    claim, each exactly what verify() answers for it. The claims are cut into one slice per
    core; the caller's thread checks the first while the pool's threads check the others."""
    cores = _cores() if _backend.RELEASES_GIL else 1
    if len(claims) < _POOL_FROM or cores < 2:
        return _verify_all(claims)
    size = -(-len(claims) // cores)
    slices = [claims[at : at + size] for at in range(0, len(claims), size)]
    pool = _verify_pool(cores - 1)
    others = [pool.submit(_verify_all, part) for part in slices[1:]]
    answers = _verify_all(slices[0])
    for other in others:
        answers += other.result()
    return answers


def _cores() -> int:
    """The cores this process may run on (its affinity, which a container's CPU set limits)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        return os.cpu_count() or 1


def _verify_all(claims: Sequence[tuple[str, bytes, str]]) -> list[bool]:
    return [verify(*claim) for claim in claims]


def _verify_pool(threads: int) -> ThreadPoolExecutor:
    global _pool
    with _POOL_LOCK:
        if _pool is None or _pool[0] != os.getpid():
            _pool = (os.getpid(), ThreadPoolExecutor(threads, thread_name_prefix="sm2-verify"))
        return _pool[1]


def _decrypt_raw(secret: int, raw: bytes) -> tuple[bytes | None, str]:
    if len(raw) <= _C2_OFFSET:
        return None, f"ciphertext is {len(raw)} bytes, too short for C1 (64), C3 (32) and data"
    c1, c3, c2 = raw[:_POINT_SIZE], raw[_POINT_SIZE:_C2_OFFSET], raw[_C2_OFFSET:]
    if not _on_curve(c1):
        return None, _C1_OFF_CURVE
    plaintext = _backend.decrypt(secret, c1, c3, c2)
    # every backend refuses a C3 mismatch (and an all-zero key stream, chance 2**-256) alike
    return (plaintext, "") if plaintext is not None else (None, _C3_MISMATCH)


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
