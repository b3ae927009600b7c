"""F9: a key an owner chose is refused unless it looks random, since its commitment and key id
are public and a guessable key is recovered from them offline. The CLI generates a key when
none is given.
"""

import json
import random
from io import StringIO

import pytest
from django.core.management import CommandError, call_command
from django.urls import reverse

from accounts.errors import InvalidKeyMaterial
from accounts.models import Owner, OwnerKey
from accounts.selectors import owner_key_bytes, owner_key_current
from accounts.services.keys import key_rotate, sm4_key_check, sm4_key_generate
from accounts.services.owners import owner_create
from smcrypto import key_id, sm4
from tests.pages.conftest import encrypted_key
from tests.support.robot_setup import TEST_PASSWORD

pytestmark = pytest.mark.django_db

WEAK_KEYS = {
    "all zeros": bytes(16),
    "one repeated byte": b"\x01" * 16,
    "two bytes repeated": bytes.fromhex("0102" * 8),
    "four bytes repeated": bytes.fromhex("deadbeef" * 4),
    # 8 distinct values, so only the pattern rule catches it.
    "eight bytes repeated": bytes.fromhex("3a9c51e07f2b64d8" * 2),
    "counting up": bytes(range(16)),
    "counting up by 0x11": bytes.fromhex("00112233445566778899aabbccddeeff"),
    "counting down": bytes(range(255, 239, -1)),
    "counting up from 0xf8, wrapping": bytes((0xF8 + n) % 256 for n in range(16)),
    "a sequence with a typo": bytes.fromhex("000102030405060708090a0bff0d0e0f"),
    "few distinct bytes": bytes.fromhex("9a9a31c4c4f0f07e7e0b0b1d1d9a31c4"),
    "a word": b"mysecretpassword",
    "a phrase with punctuation": b"Tr0ub4dor&3 xyz!",
    "a zero-padded word": b"password" + bytes(8),
    "a word after zeros": bytes(10) + b"robots",
}


@pytest.fixture
def pending_owner():
    """An owner whose chain work never runs (its queueing waits for a commit that never comes)."""

    def make(username: str) -> Owner:
        return owner_create(username=username, password=TEST_PASSWORD, sm4_key=sm4_key_generate())

    return make


@pytest.mark.parametrize("key", WEAK_KEYS.values(), ids=WEAK_KEYS.keys())
def test_owner_create_refuses_a_key_that_does_not_look_random(key):
    with pytest.raises(InvalidKeyMaterial, match="let the portal generate your key"):
        owner_create(username="carol", password=TEST_PASSWORD, sm4_key=key)
    assert not Owner.objects.exists()


@pytest.mark.parametrize("key", WEAK_KEYS.values(), ids=WEAK_KEYS.keys())
def test_key_rotation_refuses_a_key_that_does_not_look_random(pending_owner, key):
    owner = pending_owner("dora")
    with pytest.raises(InvalidKeyMaterial, match="let the portal generate your key"):
        key_rotate(owner=owner, sm4_key=key)
    assert OwnerKey.objects.filter(owner=owner).count() == 1


PUBLISHED = {
    "0123456789abcdeffedcba9876543210": "SM4 standard's published example key",
    "0123456789ABCDEFFEDCBA9876543210": "SM4 standard's published example key",
    "fedcba98765432100123456789abcdef": "SM4 test vectors' second example key",
    "681edf34d206965e86b3e94f536e4246": "SM4 standard's published example ciphertext",
    "3945208f7b2144b13f36e38ac6d39f95": "SM2 standard's published example private key",
    "66c7f0f462eeedd9d1f2d46bdc10e4e2": "SM3 standard's published example digest",
    "2b7e151628aed2a6abf7158809cf4f3c": "AES standard's published example key",
    # Not published as such, but the same hex pattern: each half counts up or down.
    "0011223344556677ffeeddccbbaa9988": "each half of this key counts",
}


@pytest.mark.parametrize("key_hex", PUBLISHED, ids=PUBLISHED.values())
def test_published_example_keys_are_refused_with_the_reason(pending_owner, key_hex):
    owner = pending_owner("dora")
    with pytest.raises(InvalidKeyMaterial, match=PUBLISHED[key_hex]):
        key_rotate(owner=owner, sm4_key=bytes.fromhex(key_hex))
    assert OwnerKey.objects.filter(owner=owner).count() == 1


def test_the_register_page_names_the_sm4_example_key(client):
    form = {
        "username": "carol",
        "password1": TEST_PASSWORD,
        "password2": TEST_PASSWORD,
        "key_ciphertext": encrypted_key(bytes.fromhex("0123456789abcdeffedcba9876543210")),
    }
    page = client.post(reverse("register"), form)
    assert page.status_code == 400
    assert "the SM4 standard&#x27;s published example key" in page.content.decode()
    assert not Owner.objects.exists()


def test_ten_thousand_random_keys_pass():
    # A seeded generator: the suite stays deterministic. The rules refuse one key in 6.5
    # million (accounts/services/keys.py), so os.urandom keys pass as well.
    rng = random.Random(20260611)
    for _ in range(10_000):
        sm4_key_check(rng.randbytes(16))


def test_generated_keys_pass_and_differ():
    keys = {sm4_key_generate() for _ in range(1000)}
    assert len(keys) == 1000
    for key in keys:
        sm4_key_check(key)


def test_the_register_page_refuses_a_typed_word_and_creates_nothing(client):
    form = {
        "username": "carol",
        "password1": TEST_PASSWORD,
        "password2": TEST_PASSWORD,
        "key_ciphertext": encrypted_key(b"mysecretpassword"),
    }
    page = client.post(reverse("register"), form)
    assert page.status_code == 400
    html = page.content.decode()
    assert "this key is text" in html
    assert "let the portal generate your key" in html
    assert not Owner.objects.exists()


def test_the_key_page_refuses_a_sequence(client, pending_owner):
    owner = pending_owner("erin")
    client.force_login(owner.user)
    form = {"password": TEST_PASSWORD, "key_ciphertext": encrypted_key(bytes(range(16)))}
    page = client.post(reverse("key-rotation"), form)
    assert page.status_code == 400
    assert "counts up or down" in page.content.decode()
    assert OwnerKey.objects.filter(owner=owner).count() == 1


def test_the_pages_generate_the_key_in_the_browser_by_default(client, pending_owner):
    html = client.get(reverse("register")).content.decode()
    assert 'id="type-own-key"' in html
    assert 'id="download-key"' in html
    assert 'id="copy-key"' in html
    script = client.get("/static/portal/keyexchange.js").getvalue().decode()
    assert "crypto.getRandomValues" in script
    assert "useGeneratedKey();" in script  # on page load
    client.force_login(pending_owner("fay").user)
    assert 'id="type-own-key"' in client.get(reverse("key-rotation")).content.decode()


# --- the CLI ------------------------------------------------------------------------------


def _owner_create(*args: str) -> dict:
    out = StringIO()
    call_command(
        "owner_create", *args, stdin=StringIO(TEST_PASSWORD + "\n"), stdout=out, stderr=StringIO()
    )
    return json.loads(out.getvalue())


def test_owner_create_without_a_key_generates_one_and_prints_it_once(deployed):
    result = _owner_create("--username", "alice")
    owner = Owner.objects.get(user__username="alice")
    key = bytes.fromhex(result["sm4_key_hex"])
    assert owner_key_bytes(owner_key_current(owner)) == key
    assert result["key_id"] == key_id(key).hex()
    assert result["chain_state"] == "confirmed"
    sm4_key_check(key)
    # A key the operator gave is not printed back.
    given = sm4.generate_key()
    assert "sm4_key_hex" not in _owner_create("--username", "bob", "--sm4-key-hex", given.hex())


@pytest.mark.parametrize(
    "key_hex", ["00112233445566778899aabbccddeeff", b"mysecretpassword".hex(), "ab" * 16]
)
def test_owner_create_refuses_a_weak_given_key_and_creates_nothing(deployed, key_hex):
    with pytest.raises(CommandError, match="let the portal generate your key"):
        _owner_create("--username", "alice", "--sm4-key-hex", key_hex)
    assert not Owner.objects.exists()


def test_demo_setup_gives_the_owner_a_generated_key(deployed, tmp_path):
    out = StringIO()
    call_command("demo_setup", "--dir", str(tmp_path), stdout=out)
    owner = Owner.objects.get(user__username=json.loads(out.getvalue())["username"])
    sm4_key_check(owner_key_bytes(owner_key_current(owner)))
    assert not (tmp_path / "sm4.key").exists()  # the robot receives it by pairing
