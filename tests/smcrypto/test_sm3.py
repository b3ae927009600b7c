"""SM3: GB/T 32905 vectors and agreement with gmssl's independent pure-Python SM3."""

from gmssl.sm3 import sm3_hash
from hypothesis import given, settings
from hypothesis import strategies as st

from smcrypto.sm3 import sm3_digest, sm3_hex


def test_gbt32905_example_1_abc() -> None:
    assert sm3_hex(b"abc") == "66c7f0f462eeedd9d1f2d46bdc10e4e24167c4875cf2f7a2297da02b8f4ba8e0"


def test_gbt32905_example_2_64_bytes() -> None:
    assert (
        sm3_hex(b"abcd" * 16) == "debe9ff92275b8a138604889c18e5a4d6fdb70e5387e5765293dcba39c0c5732"
    )


def test_empty_input() -> None:
    assert sm3_hex(b"") == "1ab21d8355cfa17f8e61194831e81a8f22bec8c728fefb747ed035eb5082aa2b"


def test_digest_is_32_bytes_and_matches_hex() -> None:
    assert len(sm3_digest(b"x")) == 32
    assert sm3_digest(b"x").hex() == sm3_hex(b"x")


@settings(max_examples=60, deadline=None)
@given(st.binary(max_size=600))
def test_agrees_with_gmssl(data: bytes) -> None:
    assert sm3_hex(data) == sm3_hash(list(data))
