"""Each event an owner can be told of reaches the owner's chosen channel, once per episode for
the watched conditions (fast: Django's in-memory mail backend, tasks run inline)."""

from datetime import timedelta

import pytest
from django.core import mail
from django.utils import timezone

from accounts.models import Robot
from accounts.services.owners import owner_create
from alerts.models import Alert, AlertDelivery, AlertKind
from alerts.services import gas_low_check, robots_silent_check
from chainworker import services as chain_services
from sharing.errors import IntegrityCheckFailed
from sharing.models import Record
from sharing.services.anchoring import record_chain_mismatch, records_anchor
from sharing.services.grants import grant_create, grant_revoke
from sharing.services.uploads import record_create
from sharing.verification.opening import record_open
from smcrypto import sm4
from stack.anvil import start_anvil
from tests.support.robot_setup import TEST_PASSWORD
from tests.support.tampering import tamper


def _alerts(owner, kind: str) -> list[Alert]:
    return list(Alert.objects.filter(owner=owner, kind=kind))


def _mails_about(kind: str) -> list:
    return [m for m in mail.outbox if m.extra_headers.get("X-AuthROS-Event") == kind]


def test_grant_received_and_revoked_tell_the_grantee(
    make_owner, alerts_on, django_capture_on_commit_callbacks
):
    alice, bob = make_owner("alice"), make_owner("bob")
    alerts_on(bob, email=[AlertKind.GRANT_RECEIVED, AlertKind.GRANT_REVOKED], address="b@x.org")
    with django_capture_on_commit_callbacks(execute=True):
        grant_create(owner=alice, grantee=bob)  # confirmed on chain inline
    [received] = _mails_about(AlertKind.GRANT_RECEIVED)
    assert received.to == ["b@x.org"]
    assert "alice granted you access" in received.body
    with django_capture_on_commit_callbacks(execute=True):
        grant_revoke(owner=alice, grantee=bob)
    [revoked] = _mails_about(AlertKind.GRANT_REVOKED)
    assert "alice revoked your access" in revoked.body
    assert not _alerts(alice, AlertKind.GRANT_RECEIVED)  # the grantee is told, not the owner
    assert AlertDelivery.objects.filter(status=AlertDelivery.Status.SENT).count() == 2


def test_a_tampered_record_is_reported_once(
    make_robot, alerts_on, upload, django_capture_on_commit_callbacks
):
    setup = make_robot()
    alerts_on(setup.owner, email=[AlertKind.RECORD_TAMPERED])
    record = upload(setup, 1)
    tamper(record)
    for _ in range(2):
        with django_capture_on_commit_callbacks(execute=True), pytest.raises(IntegrityCheckFailed):
            record_open(record_id=record.pk, viewer=setup.owner)
    [alert] = _alerts(setup.owner, AlertKind.RECORD_TAMPERED)
    assert alert.subject == str(record.pk)
    [sent] = _mails_about(AlertKind.RECORD_TAMPERED)
    assert str(record.pk) in sent.body
    assert "tampered" in sent.subject.lower()


def test_anchoring_that_gives_up_is_reported(
    make_robot, alerts_on, settings, django_capture_on_commit_callbacks
):
    setup = make_robot()
    alerts_on(setup.owner, email=[AlertKind.ANCHORING_FAILED])
    record = record_create(robot=setup.robot, data=setup.seal(1))  # anchoring not run
    Record.objects.filter(pk=record.pk).update(anchor_attempts=settings.ANCHOR_MAX_ATTEMPTS)
    with django_capture_on_commit_callbacks(execute=True):
        records_anchor(owner_id=setup.owner.pk)
    assert Record.objects.get(pk=record.pk).status == Record.Status.FAILED
    [alert] = _alerts(setup.owner, AlertKind.ANCHORING_FAILED)
    assert alert.detail["records"] == [str(record.pk)]
    assert len(_mails_about(AlertKind.ANCHORING_FAILED)) == 1
    # Another digest under a record's id (anchoring or the reconciliation finds it, perhaps
    # again and again): told once.
    other = record_create(robot=setup.robot, data=setup.seal(2))
    with django_capture_on_commit_callbacks(execute=True):
        for _ in range(2):
            record_chain_mismatch(record=other, chain_digest="ab" * 32, chain_owner="0x0")
    assert len(_alerts(setup.owner, AlertKind.ANCHORING_FAILED)) == 2
    assert "another digest" in _mails_about(AlertKind.ANCHORING_FAILED)[1].body


def test_a_silent_robot_alerts_once_per_silence(
    make_robot, alerts_on, django_capture_on_commit_callbacks
):
    setup = make_robot()
    alerts_on(setup.owner, email=[AlertKind.ROBOT_SILENT], robot_silent_minutes=10)
    heard = Robot.objects.filter(pk=setup.robot.pk)
    heard.update(last_upload_at=timezone.now() - timedelta(minutes=11))
    with django_capture_on_commit_callbacks(execute=True):
        assert robots_silent_check()["robots_silent"] == 1
        assert robots_silent_check()["robots_silent"] == 0  # the next beat: same silence
    assert len(_mails_about(AlertKind.ROBOT_SILENT)) == 1
    with django_capture_on_commit_callbacks(execute=True):
        record_create(robot=setup.robot, data=setup.seal(1))  # it speaks again
        assert robots_silent_check()["robots_back"] == 1
        heard.update(last_upload_at=timezone.now() - timedelta(minutes=30))
        assert robots_silent_check()["robots_silent"] == 1  # a new silence
    assert len(_mails_about(AlertKind.ROBOT_SILENT)) == 2
    assert setup.robot.name in _mails_about(AlertKind.ROBOT_SILENT)[0].body


def test_low_gas_alerts_once_until_topped_up(
    make_owner, alerts_on, django_capture_on_commit_callbacks
):
    owner = make_owner()
    alerts_on(owner, email=[AlertKind.GAS_LOW], gas_low_below_wei=10**30)  # more than it has
    with django_capture_on_commit_callbacks(execute=True):
        assert gas_low_check()["gas_low"] == 1
        assert gas_low_check()["gas_low"] == 0
    [sent] = _mails_about(AlertKind.GAS_LOW)
    assert owner.eoa_address in sent.body
    alerts_on(owner, email=[AlertKind.GAS_LOW], gas_low_below_wei=1)  # now it holds enough
    assert gas_low_check()["gas_topped_up"] == 1
    alerts_on(owner, email=[AlertKind.GAS_LOW], gas_low_below_wei=10**30)
    with django_capture_on_commit_callbacks(execute=True):
        assert gas_low_check()["gas_low"] == 1
    assert len(_mails_about(AlertKind.GAS_LOW)) == 2


@pytest.mark.process
def test_no_low_gas_alert_on_a_chain_that_charges_nothing_for_gas(
    db, settings, alerts_on, django_capture_on_commit_callbacks
):
    """`make run`'s anvil charges nothing for gas: EOAs hold no ether there and need none, so
    a threshold set on the alerts page never alerts (issue 35)."""
    with start_anvil(zero_gas=True) as node:
        settings.CHAIN_RPC_URL = node.url
        chain_services._clients.clear()
        chain_services.contract_deploy()
        assert chain_services.chain_client().fee_per_gas() == 0
        with django_capture_on_commit_callbacks(execute=True):
            owner = owner_create(username="lea", password=TEST_PASSWORD, sm4_key=sm4.generate_key())
        assert chain_services.chain_client().balance(owner.eoa_address) == 0
        alerts_on(owner, email=[AlertKind.GAS_LOW], gas_low_below_wei=10**18)
        with django_capture_on_commit_callbacks(execute=True):
            assert gas_low_check() == {"gas_low": 0, "gas_topped_up": 0}
        assert _mails_about(AlertKind.GAS_LOW) == []
        chain_services._clients.clear()
