import pytest

from authros_verify.values import Invalid, hash32, hashes32

STEP = "0x" + "ab" * 32


def test_a_path_reads_as_its_hashes():
    other = "0x" + "01" * 32
    assert hashes32([STEP, other], "path") == [bytes.fromhex("ab" * 32), bytes.fromhex("01" * 32)]
    assert hashes32([], "path") == []


@pytest.mark.parametrize(
    "bad",
    [
        "0x" + "AB" * 32,  # upper case
        "0x" + "ab" * 31 + " a",  # a space bytes.fromhex would skip
        "0x" + "ab" * 31 + "zz",
        "0x" + "ab" * 33,
        "ab" * 33,
        32,
        None,
    ],
)
def test_a_path_with_one_bad_step_is_refused_as_hash32_refuses_it(bad):
    with pytest.raises(Invalid, match="its path is not 0x and 64 lowercase hex digits"):
        hashes32([STEP, bad], "path")
    if isinstance(bad, str):
        with pytest.raises(Invalid):
            hash32(bad, "path")


def test_a_path_that_is_not_a_list_is_refused():
    with pytest.raises(Invalid, match="its path is not a list"):
        hashes32((STEP,), "path")
