"""SM4: GB/T 32907 and RFC 8998 vectors, CBC agreement with gmssl, clean failures."""

import random

import pytest
from gmssl.sm4 import SM4_DECRYPT, SM4_ENCRYPT, CryptSM4
from hypothesis import given, settings
from hypothesis import strategies as st

from smcrypto import sm4
from smcrypto.errors import (
    AuthenticationFailed,
    CryptoError,
    DecryptionError,
    InvalidData,
    InvalidKey,
)

# RFC 8998, Appendix A.1 (same values in nettle, GmSSL and Go's sm4 test suites)
RFC8998_KEY = bytes.fromhex("0123456789ABCDEFFEDCBA9876543210")
RFC8998_IV = bytes.fromhex("00001234567800000000ABCD")
RFC8998_AAD = bytes.fromhex("FEEDFACEDEADBEEFFEEDFACEDEADBEEFABADDAD2")
RFC8998_PLAINTEXT = bytes.fromhex(
    "AAAAAAAAAAAAAAAABBBBBBBBBBBBBBBBCCCCCCCCCCCCCCCCDDDDDDDDDDDDDDDD"
    "EEEEEEEEEEEEEEEEFFFFFFFFFFFFFFFFEEEEEEEEEEEEEEEEAAAAAAAAAAAAAAAA"
)
RFC8998_CIPHERTEXT = bytes.fromhex(
    "17F399F08C67D5EE19D0DC9969C4BB7D5FD46FD3756489069157B282BB200735"
    "D82710CA5C22F0CCFA7CBF93D496AC15A56834CBCF98C397B4024A2691233B8D"
)
RFC8998_TAG = bytes.fromhex("83DE3541E4C2B58177E065A9BF7B62EC")


def _gmssl_cbc(mode: int, key: bytes, iv: bytes, data: bytes) -> bytes:
    cipher = CryptSM4()
    cipher.set_key(key, mode)
    return cipher.crypt_cbc(iv, data)


def test_gbt32907_single_block() -> None:
    key = bytes.fromhex("0123456789abcdeffedcba9876543210")
    # with a zero IV the first CBC block is the plain block cipher output
    first_block = sm4.cbc_encrypt(key, bytes(16), key)[:16]
    assert first_block.hex() == "681edf34d206965e86b3e94f536e4246"


def test_rfc8998_gcm_encrypt() -> None:
    sealed = sm4.gcm_encrypt(RFC8998_KEY, RFC8998_IV, RFC8998_PLAINTEXT, RFC8998_AAD)
    assert sealed == RFC8998_CIPHERTEXT + RFC8998_TAG


def test_rfc8998_gcm_decrypt() -> None:
    data = RFC8998_CIPHERTEXT + RFC8998_TAG
    assert sm4.gcm_decrypt(RFC8998_KEY, RFC8998_IV, data, RFC8998_AAD) == RFC8998_PLAINTEXT


@pytest.mark.parametrize("index", [0, 31, 63, 64, 79])
def test_gcm_flipped_bit_fails_authentication(index: int) -> None:
    data = bytearray(RFC8998_CIPHERTEXT + RFC8998_TAG)
    data[index] ^= 0x01
    with pytest.raises(AuthenticationFailed):
        sm4.gcm_decrypt(RFC8998_KEY, RFC8998_IV, bytes(data), RFC8998_AAD)


def test_gcm_changed_aad_or_nonce_fails_authentication() -> None:
    data = RFC8998_CIPHERTEXT + RFC8998_TAG
    with pytest.raises(AuthenticationFailed):
        sm4.gcm_decrypt(RFC8998_KEY, RFC8998_IV, data, RFC8998_AAD + b"x")
    with pytest.raises(AuthenticationFailed):
        sm4.gcm_decrypt(RFC8998_KEY, bytes(12), data, RFC8998_AAD)


def test_one_gcm_key_decrypts_as_gcm_decrypt_and_refuses_alike() -> None:
    key = sm4.GcmKey(RFC8998_KEY)
    data = RFC8998_CIPHERTEXT + RFC8998_TAG
    for _ in range(2):  # the same key, used again
        assert key.decrypt(RFC8998_IV, data, RFC8998_AAD) == RFC8998_PLAINTEXT
    with pytest.raises(AuthenticationFailed):
        key.decrypt(RFC8998_IV, data, RFC8998_AAD + b"x")
    with pytest.raises(AuthenticationFailed):
        key.decrypt(RFC8998_IV, data[:-1] + bytes([data[-1] ^ 1]), RFC8998_AAD)
    with pytest.raises(AuthenticationFailed, match="shorter than the 16-byte tag"):
        key.decrypt(RFC8998_IV, b"\x00" * 15)
    with pytest.raises(InvalidKey):
        key.decrypt(b"short", data)
    with pytest.raises(InvalidKey):
        sm4.GcmKey(b"short")


def test_gcm_data_shorter_than_tag() -> None:
    with pytest.raises(AuthenticationFailed, match="shorter than the 16-byte tag"):
        sm4.gcm_decrypt(RFC8998_KEY, RFC8998_IV, b"\x00" * 15)


def test_gcm_empty_plaintext_round_trip() -> None:
    sealed = sm4.gcm_encrypt(RFC8998_KEY, RFC8998_IV, b"")
    assert len(sealed) == 16
    assert sm4.gcm_decrypt(RFC8998_KEY, RFC8998_IV, sealed) == b""


@settings(max_examples=40, deadline=None)
@given(
    key=st.binary(min_size=16, max_size=16),
    iv=st.binary(min_size=16, max_size=16),
    plaintext=st.binary(max_size=200),
)
def test_cbc_agrees_with_gmssl_both_ways(key: bytes, iv: bytes, plaintext: bytes) -> None:
    ours = sm4.cbc_encrypt(key, iv, plaintext)
    assert ours == _gmssl_cbc(SM4_ENCRYPT, key, iv, plaintext)
    assert _gmssl_cbc(SM4_DECRYPT, key, iv, ours) == plaintext
    assert sm4.cbc_decrypt(key, iv, ours) == plaintext


def test_cbc_decrypts_gmssl_output() -> None:
    rng = random.Random(32907)
    for size in (0, 1, 15, 16, 17, 100):
        key, iv, plaintext = rng.randbytes(16), rng.randbytes(16), rng.randbytes(size)
        assert sm4.cbc_decrypt(key, iv, _gmssl_cbc(SM4_ENCRYPT, key, iv, plaintext)) == plaintext


def test_cbc_bad_padding_is_decryption_error() -> None:
    key, iv = bytes(range(16)), bytes(16)
    ciphertext = sm4.cbc_encrypt(key, iv, b"sixteen bytes!!!")
    with pytest.raises(DecryptionError, match="padding"):
        sm4.cbc_decrypt(bytes(16), iv, ciphertext)


@pytest.mark.parametrize("length", [0, 1, 15, 17, 31])
def test_cbc_bad_length_is_decryption_error(length: int) -> None:
    with pytest.raises(DecryptionError, match="multiple of 16"):
        sm4.cbc_decrypt(bytes(16), bytes(16), b"\x00" * length)


@pytest.mark.parametrize("key", [b"", b"\x00" * 15, b"\x00" * 17, b"\x00" * 32, "0" * 16, None])
def test_bad_key_is_invalid_key(key: object) -> None:
    for call in (
        lambda: sm4.gcm_encrypt(key, bytes(12), b"x"),
        lambda: sm4.gcm_decrypt(key, bytes(12), bytes(32)),
        lambda: sm4.cbc_encrypt(key, bytes(16), b"x"),
        lambda: sm4.cbc_decrypt(key, bytes(16), bytes(16)),
    ):
        with pytest.raises(InvalidKey, match="SM4 key"):
            call()


@pytest.mark.parametrize("nonce", [b"", bytes(11), bytes(13), bytes(16)])
def test_bad_gcm_nonce(nonce: bytes) -> None:
    with pytest.raises(InvalidKey, match="nonce must be 12 bytes"):
        sm4.gcm_encrypt(bytes(16), nonce, b"x")
    with pytest.raises(InvalidKey, match="nonce must be 12 bytes"):
        sm4.gcm_decrypt(bytes(16), nonce, bytes(32))


@pytest.mark.parametrize("iv", [b"", bytes(12), bytes(15), bytes(17)])
def test_bad_cbc_iv(iv: bytes) -> None:
    with pytest.raises(InvalidKey, match="IV must be 16 bytes"):
        sm4.cbc_encrypt(bytes(16), iv, b"x")
    with pytest.raises(InvalidKey, match="IV must be 16 bytes"):
        sm4.cbc_decrypt(bytes(16), iv, bytes(16))


def test_errors_are_crypto_errors_and_value_errors() -> None:
    assert issubclass(InvalidKey, CryptoError)
    assert issubclass(CryptoError, ValueError)


def test_generate_key() -> None:
    keys = {sm4.generate_key() for _ in range(100)}
    assert len(keys) == 100
    assert all(len(key) == sm4.KEY_SIZE == 16 for key in keys)


@pytest.mark.parametrize(
    "call",
    [
        lambda: sm4.gcm_encrypt(RFC8998_KEY, bytes(12), "text"),
        lambda: sm4.gcm_encrypt(RFC8998_KEY, bytes(12), b"text", aad="header"),
        lambda: sm4.gcm_decrypt(RFC8998_KEY, bytes(12), "x" * 32),
        lambda: sm4.gcm_decrypt(RFC8998_KEY, bytes(12), bytes(32), aad=None),
        lambda: sm4.cbc_encrypt(RFC8998_KEY, bytes(16), 42),
        lambda: sm4.cbc_decrypt(RFC8998_KEY, bytes(16), "x" * 16),
    ],
)
def test_data_that_is_not_bytes_is_a_crypto_error(call) -> None:
    with pytest.raises(InvalidData, match="must be bytes"):
        call()
