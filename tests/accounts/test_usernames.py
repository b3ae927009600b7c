"""Look-alike owners (audit finding 4): `Alice`, `ALICE` and alice with a Cyrillic a could all be
registered beside `alice`, and a grant typed as `Alice` reached the look-alike. New usernames
are held apart by their skeleton (accounts.usernames); two accounts made before the rule keep
working, and a grant by a name that looks like another owner's is refused."""

import pytest
from django.apps import apps
from django.contrib.auth import get_user_model
from django.test import Client
from eth_account import Account

from accounts.errors import InvalidUsername, UsernameTaken
from accounts.models import Owner
from accounts.services.owners import owner_create
from accounts.usernames import username_skeleton
from smcrypto import sm4
from tests.api.conftest import GRANTS, token_client
from tests.support.robot_setup import TEST_PASSWORD

pytestmark = pytest.mark.django_db

CYRILLIC_ALICE = "\N{CYRILLIC SMALL LETTER A}lice"
LOOKALIKES = ["Alice", "ALICE", "a1ice", "aIice", "alIce"]
ACCENTED_ALICE = "\N{LATIN SMALL LETTER A WITH ACUTE}lice"


@pytest.mark.parametrize("name", [*LOOKALIKES, CYRILLIC_ALICE, ACCENTED_ALICE])
def test_a_name_that_looks_like_a_taken_one_has_its_skeleton(name):
    assert username_skeleton(name) == username_skeleton("alice")


@pytest.mark.parametrize(("one", "other"), [("alice", "alicia"), ("bob", "bobby"), ("rn", "rm")])
def test_different_names_have_different_skeletons(one, other):
    assert username_skeleton(one) != username_skeleton(other)


def test_rn_looks_like_m_and_vv_like_w():
    assert username_skeleton("rnary") == username_skeleton("mary")
    assert username_skeleton("vvendy") == username_skeleton("wendy")


def _create(username: str) -> Owner:
    return owner_create(username=username, password=TEST_PASSWORD, sm4_key=sm4.generate_key())


@pytest.mark.parametrize("name", LOOKALIKES)
def test_a_look_alike_of_an_owner_is_refused_as_taken(name):
    _create("alice")
    with pytest.raises(UsernameTaken, match="looks like"):
        _create(name)
    assert list(Owner.objects.values_list("user__username", flat=True)) == ["alice"]


@pytest.mark.parametrize("name", [CYRILLIC_ALICE, ACCENTED_ALICE, "al ice", "alice\x00"])
def test_a_name_outside_ascii_is_refused_and_nothing_is_made(name):
    with pytest.raises(InvalidUsername, match="ASCII"):
        _create(name)
    assert not get_user_model().objects.exists()


def test_the_registration_page_refuses_a_look_alike_with_the_reason():
    _create("alice")
    answer = Client().post(
        "/register/",
        {"username": "ALICE", "password1": TEST_PASSWORD, "password2": TEST_PASSWORD},
    )
    assert answer.status_code in (200, 400)
    assert "looks like one that is" in answer.content.decode()
    assert Owner.objects.count() == 1


def _legacy(username: str) -> Owner:
    """An owner made before the rule (as Django's default validator allowed), its skeleton
    filled in by the migration."""
    user = get_user_model().objects.create_user(username=username, password=TEST_PASSWORD)
    owner = Owner.objects.create(
        user=user, eoa_address=Account.create().address, eoa_key_wrapped=b"", name_skeleton="-"
    )
    Owner.objects.filter(pk=owner.pk).update(name_skeleton=f"legacy-{owner.pk}")
    return owner


def test_the_migration_marks_the_younger_of_two_look_alikes_and_keeps_both():
    from importlib import import_module

    alice, lookalike, carol = _legacy("alice"), _legacy(CYRILLIC_ALICE), _legacy("carol")
    import_module("accounts.migrations.0009_owner_name_skeleton").skeletons_fill(apps, None)
    marks = dict(Owner.objects.values_list("pk", "name_lookalike"))
    assert marks == {alice.pk: False, lookalike.pk: True, carol.pk: False}
    assert {o.name_skeleton for o in Owner.objects.filter(pk__in=[alice.pk, lookalike.pk])} == {
        username_skeleton("alice")
    }


def test_a_grant_by_a_name_another_owner_looks_like_is_refused_and_by_address_given(
    make_robot, make_owner_token, django_capture_on_commit_callbacks
):
    granter = make_robot("granter")
    alice = make_robot("alice")
    lookalike = make_robot("bob")  # registered on chain as any owner, then renamed as of old
    user = lookalike.owner.user
    user.username = "Alice"
    user.save(update_fields=["username"])
    Owner.objects.filter(pk=lookalike.owner.pk).update(
        name_skeleton=username_skeleton("Alice"), name_lookalike=True
    )
    client = token_client(make_owner_token(granter.owner, scopes=("read", "share"))[1])
    for typed in ("Alice", "alice"):
        with django_capture_on_commit_callbacks(execute=True):
            answer = client.post(GRANTS, {"grantee": typed}, format="json")
        assert answer.status_code == 409, answer.content
        assert answer.json()["error"] == "owner_ambiguous"
    assert not granter.owner.grants_given.exists()
    with django_capture_on_commit_callbacks(execute=True):
        answer = client.post(GRANTS, {"grantee": alice.owner.eoa_address}, format="json")
    assert answer.status_code == 201, answer.content
    assert answer.json()["grantee"] == "alice"
