"""Owners' SM4 keys: rotation, the strength check of a key an owner chose, generation.

A key is kept wrapped under the master key with its commitment, pending until
registration.py puts the commitment on chain. A key must look drawn at random: its commitment
is public, so a guessable key could be recovered offline.
"""

from collections import Counter
from itertools import pairwise

from django.db import transaction
from django.utils import timezone

from accounts import keywrap
from accounts.errors import InvalidKeyMaterial, KeyAlreadyUsed
from accounts.models import ChainState, Owner, OwnerKey
from accounts.selectors import sm4_key_purpose
from core.outbox import enqueue
from smcrypto import key_commitment, key_id, sm4


def key_rotate(*, owner: Owner, sm4_key: bytes) -> OwnerKey:
    """Make `sm4_key` the owner's current key; older keys stay to read older records."""
    sm4_key_check(sm4_key)
    with transaction.atomic():
        if owner.keys.filter(key_id=key_id(sm4_key).hex()).exists():
            raise KeyAlreadyUsed("this key was used by this owner before: choose a new one")
        owner.keys.filter(is_current=True).update(is_current=False, retired_at=timezone.now())
        new_key = owner_key_add(owner=owner, sm4_key=sm4_key)
        transaction.on_commit(lambda: enqueue("accounts.tasks.key_rotate", new_key.pk))
    return new_key


def owner_key_add(*, owner: Owner, sm4_key: bytes) -> OwnerKey:
    """`sm4_key` as the owner's new current key, wrapped, with its commitment, pending on chain.
    Within the caller's transaction, which retires the former key (key_rotate) or makes the
    owner (owner_create) and queues the chain work; the key is checked already."""
    kid = key_id(sm4_key).hex()
    return OwnerKey.objects.create(
        owner=owner,
        key_id=kid,
        key_wrapped=keywrap.wrap(sm4_key, purpose=sm4_key_purpose(owner.pk, kid)),
        commitment="0x" + key_commitment(owner.eoa_address, sm4_key).hex(),
        is_current=True,
        chain_state=ChainState.PENDING,
    )


def sm4_key_generate() -> bytes:
    """A new random SM4 key that owner_create and key_rotate take (a random key that looks
    chosen, one in millions, is drawn again)."""
    while True:
        key = sm4.generate_key()
        if _sm4_key_weakness(key) is None:
            return key


# A key an owner chose is recovered offline from its public commitment if it can be guessed,
# so a key must look drawn at random. How often each rule refuses 16 uniformly random bytes:
# fewer than 8 distinct byte values (one repeated byte included): 6.4e-13; a pattern of at
# most 8 bytes repeated: 5.4e-20; 12 or more of the 15 steps between neighbouring bytes equal
# (counting up or down: 000102..., 00112233..., ffeedd...): 1.5e-24; every byte printable
# ASCII or NUL (a word or phrase, maybe zero-padded): (96/256)**16 = 1.5e-7. So one random key
# in 6.5 million is refused (sm4_key_generate draws another); a looser text rule, such as 12
# of 16 bytes printable, would refuse one in 430. Each 8-byte half a sequence of its own
# (0123456789abcdef fedcba9876543210): 256**-12, and the published keys below: nothing.
KEY_MIN_DISTINCT_BYTES = 8
KEY_MAX_PATTERN_BYTES = 8
KEY_MAX_EQUAL_STEPS = 11
_KEY_TEXT_BYTES = frozenset(range(0x20, 0x7F)) | {0}
_LET_THE_PORTAL_GENERATE = (
    "; let the portal generate your key instead (the registration and key pages do by "
    "default; `manage.py owner_create` does without --sm4-key-hex)"
)


# Keys printed in standards and their test vectors: the first thing anyone copies, so the first
# thing an attacker tries against a commitment. Each is refused with where it was published.
PUBLISHED_KEYS: dict[bytes, str] = {
    bytes.fromhex(hex_key): where
    for hex_key, where in (
        (
            "0123456789abcdeffedcba9876543210",
            "the SM4 standard's published example key (GB/T 32907, ISO/IEC 18033-3, RFC 8998)",
        ),
        (
            "fedcba98765432100123456789abcdef",
            "the SM4 test vectors' second example key (draft-ribose-cfrg-sm4, OpenSSL's tests)",
        ),
        (
            "681edf34d206965e86b3e94f536e4246",
            "the SM4 standard's published example ciphertext (GB/T 32907 example 1)",
        ),
        (
            "595298c7c6fd271f0402f804c33d3f66",
            "the SM4 standard's published example ciphertext (GB/T 32907 example 2)",
        ),
        (
            "3945208f7b2144b13f36e38ac6d39f95",
            "the start of the SM2 standard's published example private key (GB/T 32918)",
        ),
        (
            "1649ab77a00637bd5e2efe283fbf3535",
            "the start of the SM2 standard's published example encryption key (GB/T 32918.4)",
        ),
        (
            "66c7f0f462eeedd9d1f2d46bdc10e4e2",
            'the start of the SM3 standard\'s published example digest (SM3 of "abc")',
        ),
        (
            "2b7e151628aed2a6abf7158809cf4f3c",
            "the AES standard's published example key (FIPS 197, NIST SP 800-38A)",
        ),
    )
}


def sm4_key_check(sm4_key: bytes) -> None:
    """InvalidKeyMaterial unless `sm4_key` is 16 bytes that look drawn at random."""
    if not isinstance(sm4_key, bytes) or len(sm4_key) != sm4.KEY_SIZE:
        raise InvalidKeyMaterial("an SM4 key is 16 bytes (32 hex digits)")
    weakness = _sm4_key_weakness(sm4_key)
    if weakness is not None:
        raise InvalidKeyMaterial(weakness + _LET_THE_PORTAL_GENERATE)


def _pairwise_steps(part: bytes) -> list[int]:
    """The differences (mod 256) between neighbouring bytes of `part`."""
    return [(b - a) % 256 for a, b in pairwise(part)]


def _sm4_key_weakness(key: bytes) -> str | None:
    """Why `key` looks chosen rather than random, or None."""
    if key in PUBLISHED_KEYS:
        return f"this is {PUBLISHED_KEYS[key]}, known to everyone"
    if key == bytes(len(key)):
        return "an all-zero SM4 key is not a key"
    if len(set(key)) < KEY_MIN_DISTINCT_BYTES:
        return f"this key has fewer than {KEY_MIN_DISTINCT_BYTES} different byte values"
    for period in range(1, KEY_MAX_PATTERN_BYTES + 1):
        if key[period:] == key[:-period]:
            return f"this key repeats a pattern of {period} bytes"
    steps = Counter(_pairwise_steps(key))
    if steps.most_common(1)[0][1] > KEY_MAX_EQUAL_STEPS:
        return "this key counts up or down (a sequence of bytes)"
    half = len(key) // 2
    if all(len(set(_pairwise_steps(part))) == 1 for part in (key[:half], key[half:])):
        return "each half of this key counts up or down (a hex pattern such as 0123...cdef)"
    if all(byte in _KEY_TEXT_BYTES for byte in key):
        return "this key is text (printable characters), not random bytes"
    return None
