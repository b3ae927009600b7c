"""The portal's own secrets (F6): a replaced or lost master key, or an operator key that is not
the contract's admin, make the portal refuse to serve (503, an operator message) instead of
answering 500s, and a lost master.key is never silently replaced by a new KEK."""

import logging
import os
import subprocess
import sys
from pathlib import Path

import pytest
from django.core.management import call_command
from django.core.management.base import SystemCheckError
from django.test import Client
from eth_account import Account

from accounts import keywrap
from accounts.errors import MasterKeyRefused
from accounts.models import OwnerKey, SecretFingerprint
from accounts.selectors import owner_key_bytes, owner_key_current
from accounts.services.keys import key_rotate
from accounts.services.portal_secrets import secrets_verify
from chainworker.models import Deployment
from chainworker.services import operator_account, operator_verify
from portal.middleware import service_checks_forget
from smcrypto import sm4
from stack.anvil import free_port
from tests.support.harness import wait_for
from tests.support.logs import logged_by
from tests.support.robot_setup import TEST_PASSWORD

REPO_ROOT = Path(__file__).resolve().parents[2]
RECORDS = "/api/v1/records/"


@pytest.fixture(autouse=True)
def fresh_checks(settings):
    """Each test's requests start unchecked, and leave no verdict behind for later tests."""
    service_checks_forget()
    yield
    service_checks_forget()


def _master_key_path(settings) -> Path:
    return settings.SECRETS_DIR / "master.key"


def _replace_master_key(settings) -> bytes:
    new = sm4.generate_key()
    _master_key_path(settings).write_text(new.hex() + "\n")
    return new


def _assert_refused(client: Client, *, says: str) -> None:
    api = client.get(RECORDS)
    assert api.status_code == 503
    assert api.json()["error"] == "service_misconfigured"
    assert says in api.json()["detail"]
    page = client.get("/")
    assert page.status_code == 503
    assert page["Content-Type"].startswith("text/html")
    assert says in page.content.decode()


# --- the fingerprint -------------------------------------------------------------------------


@pytest.mark.django_db
def test_the_first_use_keeps_the_fingerprint_of_the_master_key(make_owner, settings):
    assert not SecretFingerprint.objects.exists()
    make_owner()
    kept = SecretFingerprint.objects.get(name="kek")
    assert kept.fingerprint == keywrap.kek_fingerprint(keywrap.master_key())
    assert keywrap.master_key().hex() not in kept.fingerprint
    assert secrets_verify() == []


@pytest.mark.django_db
def test_a_first_start_creates_the_master_key_and_serves(settings):
    """No rows, no file: the check creates the KEK and keeps its fingerprint."""
    assert not _master_key_path(settings).exists()
    response = Client().get(RECORDS)
    assert response.status_code == 401
    assert _master_key_path(settings).stat().st_mode & 0o777 == 0o600
    assert SecretFingerprint.objects.filter(name="kek").exists()


@pytest.mark.django_db
def test_a_replaced_master_key_refuses_to_serve_with_an_operator_message(make_owner, settings):
    owner = make_owner()
    old = keywrap.master_key()
    new = _replace_master_key(settings)
    problems = secrets_verify()
    assert len(problems) == 1
    expected = keywrap.kek_fingerprint(old)[:8]
    actual = keywrap.kek_fingerprint(new)[:8]
    assert f"(fingerprint {actual}, expected {expected})" in problems[0]
    assert "restore master.key or AUTHROS_MASTER_KEY" in problems[0]

    with logged_by("portal.middleware") as logged:
        client = Client()
        _assert_refused(client, says=f"expected {expected}")
        # Logged once per check, not once per request.
        client.get("/")
    assert len(logged) == 1
    assert logged[0].levelno == logging.ERROR
    assert f"expected {expected}" in logged[0].getMessage()
    for text in (client.get(RECORDS).content, client.get("/").content):
        assert old.hex().encode() not in text
        assert new.hex().encode() not in text
    # Static files are still served (the 503 page needs none, but a proxy's health check may).
    assert client.get("/static/portal/portal.css").status_code != 503

    # Nothing is wrapped under the wrong key either: a rotation is refused outright.
    with pytest.raises(MasterKeyRefused):
        key_rotate(owner=owner, sm4_key=sm4.generate_key())
    assert OwnerKey.objects.filter(owner=owner).count() == 1

    # Restoring the key is picked up without a restart, at the next check.
    _master_key_path(settings).write_text(old.hex() + "\n")
    settings.SERVICE_CHECK_INTERVAL = 0
    assert client.get(RECORDS).status_code == 401
    assert owner_key_bytes(owner_key_current(owner))


@pytest.mark.django_db
def test_another_master_key_in_the_environment_is_refused_too(make_owner, settings):
    make_owner()
    settings.AUTHROS_MASTER_KEY = sm4.generate_key().hex()
    _assert_refused(Client(), says="does not match")


@pytest.mark.django_db
def test_a_missing_master_key_is_refused_not_created_anew(make_owner, settings):
    owner = make_owner()
    path = _master_key_path(settings)
    path.unlink()
    problems = secrets_verify()
    assert len(problems) == 1
    assert "is missing but owner keys are wrapped under it" in problems[0]
    assert not path.exists()
    # Reading an owner's key does not make a new KEK either: it is refused, clearly.
    with pytest.raises(MasterKeyRefused, match=r"restore master\.key"):
        owner_key_bytes(owner_key_current(owner))
    assert not path.exists()
    _assert_refused(Client(), says="is missing")
    assert not path.exists()


@pytest.mark.django_db
def test_a_database_from_before_fingerprints_keeps_the_key_its_rows_open_under(
    make_owner, settings
):
    make_owner()
    kek = keywrap.master_key()
    SecretFingerprint.objects.all().delete()
    assert secrets_verify() == []
    assert SecretFingerprint.objects.get(name="kek").fingerprint == keywrap.kek_fingerprint(kek)

    SecretFingerprint.objects.all().delete()
    _replace_master_key(settings)
    problems = secrets_verify()
    assert len(problems) == 1
    assert "does not open the owner keys" in problems[0]
    assert not SecretFingerprint.objects.exists()


@pytest.mark.django_db
def test_a_new_master_key_is_taken_while_nothing_is_wrapped(settings):
    assert secrets_verify() == []
    _replace_master_key(settings)
    assert secrets_verify() == []
    kept = SecretFingerprint.objects.get(name="kek").fingerprint
    assert kept == keywrap.kek_fingerprint(keywrap.master_key())


# --- the operator key ------------------------------------------------------------------------


@pytest.mark.django_db
def test_an_operator_key_that_is_not_the_contract_admin_is_refused(deployed, settings):
    admin = operator_account().address
    assert operator_verify() == []
    # operator.key lost and made anew: the portal's new operator is not the contract's admin.
    (settings.SECRETS_DIR / "operator.key").unlink()
    stranger = operator_account().address
    assert stranger != admin
    problems = operator_verify()
    assert len(problems) == 1
    assert f"the operator key (address {stranger}) is not the admin" in problems[0]
    assert f"(admin {admin})" in problems[0]
    _assert_refused(Client(), says=f"(admin {admin})")
    with pytest.raises(SystemCheckError, match="is not the admin"):
        call_command("check", databases=["default"])


@pytest.mark.django_db
def test_a_chain_that_does_not_answer_is_no_refusal(deployed, settings):
    settings.CHAIN_RPC_URL = f"http://127.0.0.1:{free_port()}"
    settings.CHAIN_OPERATOR_KEY = Account.create().key.hex()
    assert Deployment.objects.filter(is_active=True).exists()
    assert Client().get(RECORDS).status_code == 401
    call_command("check", databases=["default"])


@pytest.mark.django_db
def test_manage_py_check_reports_the_master_key_only_when_asked_with_the_database(
    make_owner, settings
):
    make_owner()
    _replace_master_key(settings)
    call_command("check")  # the checks that need no database pass, touching none
    with pytest.raises(SystemCheckError, match=r"accounts\.E101.*does not match"):
        call_command("check", databases=["default"])


# --- in fresh processes, as an operator starts them ------------------------------------------


def _environment(tmp_path: Path, **extra: str) -> dict[str, str]:
    return {
        **os.environ,
        "DJANGO_SETTINGS_MODULE": "portal.settings",
        "AUTHROS_VAR_DIR": str(tmp_path),
        "AUTHROS_SECRETS_DIR": str(tmp_path / "secrets"),
        "DATABASE_URL": f"sqlite:///{tmp_path / 'db.sqlite3'}",
        # Nothing deployed there: the chain is not asked.
        "CHAIN_RPC_URL": f"http://127.0.0.1:{free_port()}",
        "CELERY_QUEUE": f"authros-test-{tmp_path.name}",
        "REDIS_KEY_PREFIX": f"authros-test-{tmp_path.name}",
        "AUTHROS_MASTER_KEY": "",
        "PYTHONUNBUFFERED": "1",
        **extra,
    }


def _manage(env: dict[str, str], *args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "manage.py", *args],
        cwd=REPO_ROOT,
        env=env,
        capture_output=True,
        text=True,
        timeout=180,
        check=False,
    )


WRAP_ONE_OWNER_KEY = f"""
from django.contrib.auth import get_user_model
from eth_account import Account
from accounts import keywrap
from accounts.models import Owner, OwnerKey
user = get_user_model().objects.create_user(username="alice", password="{TEST_PASSWORD}")
owner = Owner.objects.create(
    user=user, eoa_address=Account.create().address, eoa_key_wrapped=b""
)
key = keywrap.wrap(bytes(16), purpose=keywrap.sm4_key_purpose(owner.pk, "00"))
OwnerKey.objects.create(owner=owner, key_id="00", key_wrapped=key, commitment="0x00")
"""


@pytest.mark.process
def test_a_fresh_install_migrates_and_checks_clean_then_a_lost_key_stops_the_worker(tmp_path):
    env = _environment(tmp_path)
    migrated = _manage(env, "migrate", "--noinput")
    assert migrated.returncode == 0, migrated.stderr
    checked = _manage(env, "check", "--database", "default")
    assert checked.returncode == 0, checked.stderr
    assert (tmp_path / "secrets" / "master.key").exists()
    made = _manage(env, "shell", "-c", WRAP_ONE_OWNER_KEY)
    assert made.returncode == 0, made.stderr

    # The KEK is lost: `check` says so, and a worker refuses to start.
    (tmp_path / "secrets" / "master.key").unlink()
    checked = _manage(env, "check", "--database", "default")
    assert checked.returncode != 0
    assert "is missing but owner keys are wrapped under it" in checked.stderr
    worker = subprocess.run(
        [sys.executable, "-m", "celery", "-A", "portal", "worker", "-c", "1", "-l", "INFO"],
        cwd=REPO_ROOT,
        env=env,
        capture_output=True,
        text=True,
        timeout=180,
        check=False,
    )
    assert worker.returncode == 78
    assert "the worker refuses to start until an operator fixes this" in worker.stderr
    assert "is missing but owner keys are wrapped under it" in worker.stderr
    assert not (tmp_path / "secrets" / "master.key").exists()


@pytest.mark.process
def test_a_worker_with_the_right_keys_starts(tmp_path):
    env = _environment(tmp_path)
    assert _manage(env, "migrate", "--noinput").returncode == 0
    assert _manage(env, "shell", "-c", WRAP_ONE_OWNER_KEY).returncode == 0
    log = tmp_path / "worker.log"
    with log.open("w") as output:
        worker = subprocess.Popen(
            [sys.executable, "-m", "celery", "-A", "portal", "worker", "-c", "1", "-l", "INFO"],
            cwd=REPO_ROOT,
            env=env,
            stdout=output,
            stderr=subprocess.STDOUT,
        )
        try:
            wait_for(
                lambda: "ready." in log.read_text() or worker.poll() is not None,
                timeout=120,
                what="the worker to start",
            )
            assert worker.poll() is None, log.read_text()
        finally:
            worker.terminate()
            worker.wait(timeout=60)
    assert "refuses to start" not in log.read_text()
