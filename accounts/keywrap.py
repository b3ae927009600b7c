"""Secrets at rest wrapped under the portal master key (KEK) with SM4-GCM.

A wrapped blob is `version(1) || nonce(12) || ciphertext || tag(16)`; the AAD binds it to
its purpose (e.g. "sm4-key:<owner id>:<key id>"), so a blob copied to another row does not
unwrap.

The database keeps the KEK's fingerprint (SecretFingerprint "kek"), never the KEK: a portal
started with another KEK than the one its rows were wrapped under refuses to wrap anything
(`kek_verify`, run before serving), and a missing master.key is not replaced by a new one
while rows are wrapped under the old one.
"""

import secrets

from django.conf import settings
from django.db import IntegrityError, transaction

from accounts.errors import MasterKeyRefused
from accounts.models import Owner, OwnerKey, SecretFingerprint
from core.secrets import SecretFileError, load_or_create_secret
from smcrypto import CryptoError, sm3, sm4

WRAP_VERSION = 1
_NONCE_SIZE = sm4.GCM_NONCE_SIZE
KEK_FINGERPRINT = "kek"
# Enough of a fingerprint for an operator to tell two keys apart; it is no secret either way.
FINGERPRINT_SHOWN = 8


class UnwrapFailed(Exception):
    """A wrapped secret does not open under the master key (wrong KEK, or changed data)."""


def master_key() -> bytes:
    """The KEK: AUTHROS_MASTER_KEY, else master.key, created only while nothing is wrapped."""
    configured = settings.AUTHROS_MASTER_KEY
    if configured:
        try:
            key = bytes.fromhex(configured)
        except ValueError:
            key = b""
        if len(key) != sm4.KEY_SIZE:
            raise MasterKeyRefused("AUTHROS_MASTER_KEY must be 32 hex digits (an SM4 key)")
        return key
    path = settings.SECRETS_DIR / "master.key"
    if not path.exists() and _wrapped_rows_exist():
        raise MasterKeyRefused(
            f"the master key file {path} is missing but owner keys are wrapped under it: "
            "restore master.key (or set AUTHROS_MASTER_KEY); a new key would open none of them"
        )
    try:
        return load_or_create_secret(path, nbytes=sm4.KEY_SIZE)
    except SecretFileError as exc:
        raise MasterKeyRefused(str(exc)) from None


def kek_fingerprint(kek: bytes) -> str:
    """SM3 over a domain tag and the KEK, in hex: tells KEKs apart without revealing them."""
    return sm3.sm3_hex(b"AuthROS/kek-fingerprint/v1" + kek)


def kek_verify() -> None:
    """Raise MasterKeyRefused unless the KEK is the one the stored rows were wrapped under.

    The first time (no fingerprint kept yet) the KEK's fingerprint is kept: at once when
    nothing is wrapped, else only if a wrapped row opens under it (a database from before
    fingerprints).
    """
    _kek_settle(master_key())


def wrap(secret: bytes, *, purpose: str) -> bytes:
    kek = master_key()
    _kek_settle(kek)
    nonce = secrets.token_bytes(_NONCE_SIZE)
    aad = _aad(purpose)
    return bytes([WRAP_VERSION]) + nonce + sm4.gcm_encrypt(kek, nonce, secret, aad)


def unwrap(blob: bytes, *, purpose: str) -> bytes:
    return _unwrap(blob, purpose=purpose, kek=master_key())


def eoa_purpose(owner_pk: int) -> str:
    return f"eoa-key:{owner_pk}"


def sm4_key_purpose(owner_pk: int, key_id: str) -> str:
    return f"sm4-key:{owner_pk}:{key_id}"


def _unwrap(blob: bytes, *, purpose: str, kek: bytes) -> bytes:
    blob = bytes(blob)
    if len(blob) < 1 + _NONCE_SIZE + sm4.GCM_TAG_SIZE or blob[0] != WRAP_VERSION:
        raise UnwrapFailed(f"not a wrapped secret (purpose {purpose})")
    nonce, data = blob[1 : 1 + _NONCE_SIZE], blob[1 + _NONCE_SIZE :]
    try:
        return sm4.gcm_decrypt(kek, nonce, data, _aad(purpose))
    except CryptoError as exc:
        raise UnwrapFailed(f"wrapped secret for {purpose} does not open under the KEK") from exc


def _kek_settle(kek: bytes) -> None:
    fingerprint = kek_fingerprint(kek)
    kept = SecretFingerprint.objects.filter(name=KEK_FINGERPRINT).first()
    if kept is not None and kept.fingerprint == fingerprint:
        return
    if not _wrapped_rows_exist():
        # Nothing is wrapped yet: whichever KEK this is, it is the one from now on.
        SecretFingerprint.objects.update_or_create(
            name=KEK_FINGERPRINT, defaults={"fingerprint": fingerprint}
        )
        return
    shown = fingerprint[:FINGERPRINT_SHOWN]
    if kept is not None:
        raise MasterKeyRefused(
            "the master key does not match the one the owner keys were wrapped with "
            f"(fingerprint {shown}, expected {kept.fingerprint[:FINGERPRINT_SHOWN]}): "
            "restore master.key or AUTHROS_MASTER_KEY"
        )
    if not _opens_oldest_wrapped_key(kek):
        raise MasterKeyRefused(
            "the master key does not open the owner keys wrapped before fingerprints were kept "
            f"(fingerprint {shown}): restore master.key or AUTHROS_MASTER_KEY"
        )
    try:
        with transaction.atomic():
            SecretFingerprint.objects.create(name=KEK_FINGERPRINT, fingerprint=fingerprint)
    except IntegrityError:
        pass  # another process kept it first: the same KEK, as the key opened for both


def _wrapped_rows_exist() -> bool:
    # An owner's EOA key is wrapped in the transaction that adds its first OwnerKey; the
    # owner row itself exists a moment earlier, still without a wrapped key.
    return OwnerKey.objects.exists() or Owner.objects.exclude(eoa_key_wrapped=b"").exists()


def _opens_oldest_wrapped_key(kek: bytes) -> bool:
    """Whether the first owner key ever wrapped (under the original KEK) opens under `kek`."""
    oldest = OwnerKey.objects.order_by("created_at", "pk").first()
    if oldest is None:
        owner = Owner.objects.exclude(eoa_key_wrapped=b"").order_by("created_at", "pk").first()
        blob, purpose = owner.eoa_key_wrapped, eoa_purpose(owner.pk)
    else:
        blob, purpose = oldest.key_wrapped, sm4_key_purpose(oldest.owner_id, oldest.key_id)
    try:
        _unwrap(blob, purpose=purpose, kek=kek)
    except UnwrapFailed:
        return False
    return True


def _aad(purpose: str) -> bytes:
    return b"AuthROS/keywrap/v1|" + purpose.encode()
