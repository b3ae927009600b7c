"""The paper's key exchange: owners send their SM4 key encrypted to the portal's SM2 key.

The portal's SM2 key pair comes from AUTHROS_SM2_PRIVATE_KEY (64 hex digits) or a 0600 file
created on first use. The public key is served as `04||x||y` hex; ciphertexts are C1C3C2 hex
(what gmssl mode=1 and the npm sm-crypto with cipherMode 1 produce).
"""

from django.conf import settings

from accounts.errors import InvalidKeyMaterial
from core.secrets import load_or_create_secret
from smcrypto import CryptoError, sm2, sm4


def portal_sm2_private_key() -> str:
    configured = settings.AUTHROS_SM2_PRIVATE_KEY
    if configured:
        return configured.lower()
    secret = load_or_create_secret(settings.SECRETS_DIR / "sm2-private.key", nbytes=32)
    return secret.hex()


def portal_sm2_public_key() -> str:
    """The portal's SM2 public key, `04||x||y` as 130 hex digits."""
    return sm2.public_key_from_private(portal_sm2_private_key())


def sm4_key_from_submission(ciphertext_hex: str) -> bytes:
    """Decrypt an SM4 key that a browser or CLI encrypted to the portal's SM2 key."""
    try:
        key = sm2.decrypt(portal_sm2_private_key(), ciphertext_hex.strip())
    except CryptoError:
        raise InvalidKeyMaterial(
            "the key could not be decrypted: encrypt it to the portal's current SM2 public key"
        ) from None
    if len(key) != sm4.KEY_SIZE:
        raise InvalidKeyMaterial("the decrypted key is not 16 bytes (32 hex digits)")
    return key
