"""Secrets at rest wrapped under the portal master key (KEK) with SM4-GCM.

A wrapped blob is `version(1) || nonce(12) || ciphertext || tag(16)`; the AAD binds it to
its purpose (e.g. "sm4-key:<owner id>"), so a blob copied to another row does not unwrap.
"""

import secrets

from django.conf import settings

from core.secrets import load_or_create_secret
from smcrypto import CryptoError, sm4

WRAP_VERSION = 1
_NONCE_SIZE = sm4.GCM_NONCE_SIZE


class UnwrapFailed(Exception):
    """A wrapped secret does not open under the master key (wrong KEK, or changed data)."""


def master_key() -> bytes:
    configured = settings.AUTHROS_MASTER_KEY
    if configured:
        key = bytes.fromhex(configured)
        if len(key) != sm4.KEY_SIZE:
            raise ValueError("AUTHROS_MASTER_KEY must be 32 hex digits (an SM4 key)")
        return key
    return load_or_create_secret(settings.SECRETS_DIR / "master.key", nbytes=sm4.KEY_SIZE)


def wrap(secret: bytes, *, purpose: str) -> bytes:
    nonce = secrets.token_bytes(_NONCE_SIZE)
    aad = _aad(purpose)
    return bytes([WRAP_VERSION]) + nonce + sm4.gcm_encrypt(master_key(), nonce, secret, aad)


def unwrap(blob: bytes, *, purpose: str) -> bytes:
    blob = bytes(blob)
    if len(blob) < 1 + _NONCE_SIZE + sm4.GCM_TAG_SIZE or blob[0] != WRAP_VERSION:
        raise UnwrapFailed(f"not a wrapped secret (purpose {purpose})")
    nonce, data = blob[1 : 1 + _NONCE_SIZE], blob[1 + _NONCE_SIZE :]
    try:
        return sm4.gcm_decrypt(master_key(), nonce, data, _aad(purpose))
    except CryptoError as exc:
        raise UnwrapFailed(f"wrapped secret for {purpose} does not open under the KEK") from exc


def _aad(purpose: str) -> bytes:
    return b"AuthROS/keywrap/v1|" + purpose.encode()
