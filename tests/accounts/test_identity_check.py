"""The identity check: the key commitment on chain is compared with the key the portal holds
when a registration or rotation is confirmed, before uploads and before views; a commitment
changed on chain behind the portal's back refuses both (409) and is written down once."""

import logging
import time
from collections.abc import Callable

import pytest
from django.test import Client

from accounts import identity as identity_module
from accounts.errors import IdentityMismatch
from accounts.identity import owner_identity_check
from accounts.models import AccountEvent, ChainState, Owner
from accounts.selectors import owner_eoa_account, owner_key_current
from accounts.services.keys import key_rotate
from accounts.services.registration import owner_register_on_chain
from chainworker.client import AuthROSChain
from chainworker.services import chain_client, contract_deploy
from portal.celery import app as celery_app
from sharing.models import Record
from smcrypto import key_commitment, sm4
from stack.anvil import free_port
from tests.api.conftest import RECORDS, Snapshot, b64, session_client, token_client
from tests.support.logs import logged_by
from tests.support.robot_setup import RobotSetup, seal_for

pytestmark = pytest.mark.django_db


@pytest.fixture
def post(django_capture_on_commit_callbacks) -> Callable:
    """Upload as the robot; anchoring (queued on commit) runs inline."""

    def send(setup: RobotSetup, seq: int):
        with django_capture_on_commit_callbacks(execute=True):
            return token_client(setup.token).post(
                RECORDS, {"envelope": b64(setup.seal(seq))}, format="json"
            )

    return send


def _commitment_changed_behind_the_portals_back(client: AuthROSChain, owner: Owner) -> bytes:
    """The owner's EOA registers another key's commitment on chain (rotateKey), as whoever
    took the EOA's key could: the portal's rows are not told."""
    other = key_commitment(owner.eoa_address, sm4.generate_key())
    client.rotate_key(owner_eoa_account(owner), other)
    return other


def _calls_counted(client: AuthROSChain, name: str, monkeypatch) -> list[str]:
    calls: list[str] = []
    method = getattr(client, name)

    def counted(*args: object, **kwargs: object) -> object:
        calls.append(name)
        return method(*args, **kwargs)

    monkeypatch.setattr(client, name, counted)
    return calls


def test_a_commitment_changed_on_chain_refuses_uploads_and_views(
    make_robot, deployed, post, settings
):
    settings.IDENTITY_BLOCK_CACHE_SECONDS = 0  # the change is seen at the next block
    robot = make_robot()
    owner = robot.owner
    browser = Client()
    browser.force_login(owner.user)
    api = session_client(owner)

    # Before the change: uploads and views work.
    answer = post(robot, 1)
    assert answer.status_code == 201, answer.content
    record = Record.objects.get(pk=answer.json()["id"])
    assert api.get(f"{RECORDS}{record.id}/content/").status_code == 200
    assert browser.get(f"/records/{record.id}/").status_code == 200
    assert owner_identity_check(owner=owner) is True

    other = _commitment_changed_behind_the_portals_back(deployed, owner)
    snapshot = Snapshot()
    with logged_by("authros.security") as logged:
        refused = post(robot, 2)
        assert refused.status_code == 409
        assert refused.json()["error"] == "identity_check_failed"
        assert f"the key commitment on chain for {owner}" in refused.json()["detail"]
        assert snapshot.unchanged()

        content = api.get(f"{RECORDS}{record.id}/content/")
        assert content.status_code == 409
        assert content.json()["error"] == "identity_check_failed"
        page = browser.get(f"/records/{record.id}/")
        assert page.status_code == 409
        assert "Identity check failed" in page.content.decode()
        assert "differs from the key the portal holds" in page.content.decode()
        raw = browser.get(f"/records/{record.id}/raw.json")
        assert raw.status_code == 409
        assert raw.json()["error"] == "identity_check_failed"

    # Written down once for this commitment, not once per refusal.
    events = AccountEvent.objects.filter(owner=owner, kind=AccountEvent.Kind.IDENTITY_MISMATCH)
    assert events.count() == 1
    assert events.get().detail == {
        "chain_commitment": "0x" + other.hex(),
        "expected_commitment": owner_key_current(owner).commitment,
    }
    assert len(logged) == 1
    assert logged[0].levelno == logging.ERROR
    assert "identity check failed" in logged[0].getMessage()
    assert "0x" + other.hex() in logged[0].getMessage()

    # Another commitment again is another event.
    _commitment_changed_behind_the_portals_back(deployed, owner)
    assert post(robot, 3).status_code == 409
    assert events.count() == 2


def test_the_check_costs_no_chain_call_per_request_once_cached(
    make_robot, deployed, settings, monkeypatch
):
    settings.IDENTITY_BLOCK_CACHE_SECONDS = 3600
    robot = make_robot()
    uploads = token_client(robot.token)
    assert uploads.post(RECORDS, {"envelope": b64(robot.seal(1))}, format="json").status_code == 201
    client = chain_client()
    calls = _calls_counted(client, "commitment_of", monkeypatch)
    calls += _calls_counted(client, "latest_block", monkeypatch)
    for seq in range(2, 7):
        answer = uploads.post(RECORDS, {"envelope": b64(robot.seal(seq))}, format="json")
        assert answer.status_code == 201
    assert calls == []


def test_a_process_keeps_the_cached_answer_until_its_redis_entry_expires(
    make_robot, deployed, settings, monkeypatch
):
    """No round trip to Redis per request: this process reuses what it read for as long as
    the Redis entry it read has left, then reads Redis again (so it is never staler than any
    other process's answer), and asks the chain only once the entry is gone."""
    settings.IDENTITY_BLOCK_CACHE_SECONDS = 2.0
    robot = make_robot()
    client = chain_client()
    asked = _calls_counted(client, "commitment_of", monkeypatch)
    read = []
    real_read = identity_module._cache_get
    monkeypatch.setattr(
        identity_module, "_cache_get", lambda key: read.append(key) or real_read(key)
    )
    identity_module._known.clear()
    assert owner_identity_check(owner=robot.owner, fresh=True) is True  # in Redis, 2 s
    assert len(asked) == 1
    identity_module._known.clear()  # another process: its first check reads Redis's entry
    for _ in range(5):
        assert owner_identity_check(owner=robot.owner) is True
    assert (len(read), len(asked)) == (1, 1)  # read once, then kept
    time.sleep(2.1)
    for _ in range(3):
        assert owner_identity_check(owner=robot.owner) is True
    assert (len(read), len(asked)) == (2, 2)  # both expired: Redis empty, the chain once
    identity_module._known.clear()
    assert owner_identity_check(owner=robot.owner) is True
    assert (len(read), len(asked)) == (3, 2)  # read from Redis, kept for what it has left
    assert owner_identity_check(owner=robot.owner) is True
    assert len(read) == 3
    time.sleep(2.1)
    assert owner_identity_check(owner=robot.owner) is True
    assert (len(read), len(asked)) == (4, 3)


def test_a_commitment_changed_on_chain_is_refused_once_the_kept_answer_expires(
    make_robot, deployed, settings, post
):
    settings.IDENTITY_BLOCK_CACHE_SECONDS = 0.5
    robot = make_robot()
    assert post(robot, 1).status_code == 201
    _commitment_changed_behind_the_portals_back(deployed, robot.owner)
    time.sleep(0.6)
    assert post(robot, 2).status_code == 409


def test_the_commitment_is_asked_once_per_block(make_robot, deployed, settings, monkeypatch):
    """Without the short-lived latest block, each request asks only for the block number."""
    settings.IDENTITY_BLOCK_CACHE_SECONDS = 0
    robot = make_robot()
    client = chain_client()
    asked = _calls_counted(client, "commitment_of", monkeypatch)
    for _ in range(5):
        assert owner_identity_check(owner=robot.owner) is True
    assert len(asked) <= 1
    # A new block: asked again, once.
    client.dev_faucet(robot.owner.eoa_address, 1)
    for _ in range(5):
        assert owner_identity_check(owner=robot.owner) is True
    assert len(asked) <= 2


def test_a_rotation_is_checked_when_confirmed_without_a_false_alarm(
    make_robot, deployed, settings, django_capture_on_commit_callbacks
):
    """The latest block is cached from before the rotation: the check asks the chain again
    before it calls a mismatch."""
    settings.IDENTITY_BLOCK_CACHE_SECONDS = 3600
    robot = make_robot()
    owner = robot.owner
    assert owner_identity_check(owner=owner) is True
    new_key = sm4.generate_key()
    with django_capture_on_commit_callbacks(execute=True):
        key_rotate(owner=owner, sm4_key=new_key)
    assert owner_key_current(owner).chain_state == ChainState.CONFIRMED
    assert owner_identity_check(owner=owner) is True
    upload = seal_for(robot.robot, new_key, seq=1)
    answer = token_client(robot.token).post(RECORDS, {"envelope": b64(upload)}, format="json")
    assert answer.status_code == 201
    assert not AccountEvent.objects.filter(kind=AccountEvent.Kind.IDENTITY_MISMATCH).exists()


def test_a_registration_confirmed_against_another_commitment_is_refused(make_owner, deployed):
    owner = make_owner()
    _commitment_changed_behind_the_portals_back(deployed, owner)
    Owner.objects.filter(pk=owner.pk).update(chain_state=ChainState.PENDING)
    with pytest.raises(IdentityMismatch):
        owner_register_on_chain(owner_id=owner.pk)
    assert AccountEvent.objects.filter(
        owner=owner, kind=AccountEvent.Kind.IDENTITY_MISMATCH
    ).exists()


def test_an_owner_not_on_chain_yet_is_not_checked(make_owner, deployed, monkeypatch):
    owner = make_owner()
    Owner.objects.filter(pk=owner.pk).update(chain_state=ChainState.PENDING)
    owner.refresh_from_db()
    asked = _calls_counted(chain_client(), "commitment_of", monkeypatch)
    assert owner_identity_check(owner=owner) is False
    assert asked == []


def test_an_owner_the_chain_lost_is_not_a_mismatch(make_robot, deployed, fresh_chain):
    """After a chain reset (or lost blocks) the owner has no commitment on the live chain:
    reconciliation registers it again; meanwhile uploads go on and nothing is written down as
    a changed key."""
    robot = make_robot()
    assert owner_identity_check(owner=robot.owner, fresh=True) is True
    fresh_chain()
    contract_deploy(force=True)
    assert not chain_client().is_registered(robot.owner.eoa_address)
    assert owner_identity_check(owner=robot.owner, fresh=True) is False
    answer = token_client(robot.token).post(
        RECORDS, {"envelope": b64(robot.seal(1))}, format="json"
    )
    assert answer.status_code == 201
    assert not AccountEvent.objects.filter(kind=AccountEvent.Kind.IDENTITY_MISMATCH).exists()


def test_a_chain_that_does_not_answer_does_not_stop_uploads(make_robot, settings):
    robot = make_robot()
    settings.CHAIN_RPC_URL = f"http://127.0.0.1:{free_port()}"
    assert owner_identity_check(owner=robot.owner) is False
    answer = token_client(robot.token).post(
        RECORDS, {"envelope": b64(robot.seal(1))}, format="json"
    )
    assert answer.status_code == 201


def test_the_workers_refusal_reaches_the_web_process_as_itself():
    """A view's check runs in a worker: its IdentityMismatch crosses the result backend (JSON)
    and is raised again as itself, so that the view answers 409, not 503."""
    backend = celery_app.backend
    refusal = IdentityMismatch("the key commitment on chain for alice differs")
    stored = backend.prepare_exception(refusal, serializer="json")
    again = backend.exception_to_python(stored)
    assert isinstance(again, IdentityMismatch)
    assert str(again) == str(refusal)
