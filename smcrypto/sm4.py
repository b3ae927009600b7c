"""SM4 block cipher (GB/T 32907) in GCM and CBC modes through cryptography/OpenSSL."""

import secrets

from cryptography.exceptions import InvalidTag
from cryptography.hazmat.primitives import padding
from cryptography.hazmat.primitives.ciphers import Cipher, algorithms, modes

from smcrypto.errors import AuthenticationFailed, DecryptionError, InvalidData, InvalidKey

KEY_SIZE = 16
BLOCK_SIZE = 16
GCM_NONCE_SIZE = 12
GCM_TAG_SIZE = 16
CBC_IV_SIZE = 16


def generate_key() -> bytes:
    """Return a fresh random 16-byte SM4 key."""
    return secrets.token_bytes(KEY_SIZE)


def gcm_encrypt(key: bytes, nonce: bytes, plaintext: bytes, aad: bytes = b"") -> bytes:
    """Encrypt with SM4-GCM; return ciphertext followed by the 16-byte tag."""
    encryptor = Cipher(algorithms.SM4(_check_key(key)), modes.GCM(_check_nonce(nonce))).encryptor()
    encryptor.authenticate_additional_data(_check_data(aad, "SM4-GCM associated data"))
    ciphertext = (
        encryptor.update(_check_data(plaintext, "SM4-GCM plaintext")) + encryptor.finalize()
    )
    return ciphertext + encryptor.tag


def gcm_decrypt(key: bytes, nonce: bytes, data: bytes, aad: bytes = b"") -> bytes:
    """Decrypt ciphertext||tag from gcm_encrypt; raise AuthenticationFailed if it was changed."""
    return GcmKey(key).decrypt(nonce, data, aad)


class GcmKey:
    """One SM4 key for SM4-GCM decryption of many messages: the key checked and its cipher
    algorithm made once (gcm_decrypt makes both per message). Lives as long as its caller
    holds the key."""

    __slots__ = ("_algorithm",)

    def __init__(self, key: bytes) -> None:
        self._algorithm = algorithms.SM4(_check_key(key))

    def decrypt(self, nonce: bytes, data: bytes, aad: bytes = b"") -> bytes:
        """gcm_decrypt under this key."""
        nonce = _check_nonce(nonce)
        data = _check_data(data, "SM4-GCM data")
        aad = _check_data(aad, "SM4-GCM associated data")
        if len(data) < GCM_TAG_SIZE:
            raise AuthenticationFailed(
                f"SM4-GCM data is {len(data)} bytes, shorter than the {GCM_TAG_SIZE}-byte tag"
            )
        decryptor = Cipher(self._algorithm, modes.GCM(nonce, data[-GCM_TAG_SIZE:])).decryptor()
        decryptor.authenticate_additional_data(aad)
        plaintext = decryptor.update(data[:-GCM_TAG_SIZE])
        try:
            return plaintext + decryptor.finalize()
        except InvalidTag:
            raise AuthenticationFailed(
                "SM4-GCM authentication failed: the data, its header or the key is not the one "
                "sealed"
            ) from None


def cbc_encrypt(key: bytes, iv: bytes, plaintext: bytes) -> bytes:
    """Encrypt with SM4-CBC and PKCS#7 padding (unauthenticated: for interoperability only)."""
    padder = padding.PKCS7(BLOCK_SIZE * 8).padder()
    padded = padder.update(_check_data(plaintext, "SM4-CBC plaintext")) + padder.finalize()
    encryptor = Cipher(algorithms.SM4(_check_key(key)), modes.CBC(_check_iv(iv))).encryptor()
    return encryptor.update(padded) + encryptor.finalize()


def cbc_decrypt(key: bytes, iv: bytes, ciphertext: bytes) -> bytes:
    """Decrypt SM4-CBC and strip PKCS#7 padding; raise DecryptionError on bad length or padding."""
    key = _check_key(key)
    iv = _check_iv(iv)
    ciphertext = _check_data(ciphertext, "SM4-CBC ciphertext")
    if not ciphertext or len(ciphertext) % BLOCK_SIZE:
        raise DecryptionError(
            f"SM4-CBC ciphertext must be a non-zero multiple of {BLOCK_SIZE} bytes, "
            f"got {len(ciphertext)}"
        )
    decryptor = Cipher(algorithms.SM4(key), modes.CBC(iv)).decryptor()
    padded = decryptor.update(ciphertext) + decryptor.finalize()
    unpadder = padding.PKCS7(BLOCK_SIZE * 8).unpadder()
    try:
        return unpadder.update(padded) + unpadder.finalize()
    except ValueError:
        raise DecryptionError(
            "SM4-CBC padding is invalid: wrong key or IV, or corrupted ciphertext"
        ) from None


def _check_key(key: bytes) -> bytes:
    return _check_length(key, KEY_SIZE, "SM4 key")


def _check_nonce(nonce: bytes) -> bytes:
    return _check_length(nonce, GCM_NONCE_SIZE, "SM4-GCM nonce")


def _check_iv(iv: bytes) -> bytes:
    return _check_length(iv, CBC_IV_SIZE, "SM4-CBC IV")


def _check_length(value: bytes, size: int, what: str) -> bytes:
    if not isinstance(value, bytes | bytearray | memoryview):
        raise InvalidKey(f"{what} must be bytes, got {type(value).__name__}")
    value = bytes(value)
    if len(value) != size:
        raise InvalidKey(f"{what} must be {size} bytes, got {len(value)}")
    return value


def _check_data(value: bytes, what: str) -> bytes:
    if not isinstance(value, bytes | bytearray | memoryview):
        raise InvalidData(f"{what} must be bytes, got {type(value).__name__}")
    return bytes(value)
