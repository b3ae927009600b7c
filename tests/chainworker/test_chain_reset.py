"""Chain reset detection: the node compared with the active deployment, and what the portal
does on a real network (stops sending and tells the operator)."""

import logging

import pytest
from django.core.management import call_command
from django.urls import reverse

from accounts.services import owner_top_up
from chainworker import services as chain_services
from chainworker.models import Deployment
from chainworker.work import ChainWorkNotReady
from sharing import anchoring
from sharing.models import Grant, Record
from sharing.reconcile import chain_reconcile
from sharing.services import grant_create, grant_sync_on_chain, record_create
from tests.conftest import logged_by

pytestmark = pytest.mark.django_db


def test_identity_before_and_after_deployment(db):
    assert chain_services.chain_identity().state == "undeployed"
    chain_services.contract_deploy()
    identity = chain_services.chain_identity()
    assert (identity.state, identity.development) == ("same", True)


def test_another_genesis_is_a_reset(deployed):
    Deployment.objects.update(genesis_hash="0x" + "ab" * 32)
    identity = chain_services.chain_identity()
    assert identity.state == "reset"
    assert "genesis" in identity.reason


def test_no_code_at_the_address_is_a_reset(deployed):
    Deployment.objects.update(address="0x" + "12" * 20)
    identity = chain_services.chain_identity()
    assert identity.state == "reset"
    assert "no contract code" in identity.reason


def test_on_a_real_network_a_reset_stops_sending_and_says_why(
    make_robot, make_owner, fresh_chain, settings, capsys, admin_client
):
    setup = make_robot("alice")
    bob = make_owner("bob")
    record = record_create(robot=setup.robot, data=setup.seal(1))  # anchoring not run
    grant = grant_create(owner=setup.owner, grantee=bob)
    fresh_chain()
    settings.CHAIN_DEV_FAUCET = False  # a real network: no faucet, no redeployment by itself

    with logged_by("sharing.reconcile") as seen:
        outcome = chain_reconcile()
    assert outcome["identity"] == "reset"
    assert any(
        r.levelno == logging.ERROR and "chain reset detected" in r.getMessage() for r in seen
    )
    assert Deployment.objects.count() == 1  # nothing deployed by itself

    with pytest.raises(ChainWorkNotReady, match="sending is stopped: the node is chain id"):
        anchoring.records_anchor(owner_id=setup.owner.pk)
    with pytest.raises(ChainWorkNotReady, match="sending is stopped"):
        grant_sync_on_chain(grant_id=grant.pk)
    with pytest.raises(ChainWorkNotReady, match="sending is stopped"):
        owner_top_up(owner_id=setup.owner.pk)  # no ether to a chain that is not ours
    record.refresh_from_db()
    assert (record.status, record.anchor_attempts) == (Record.Status.PENDING, 0)
    assert Grant.objects.get(pk=grant.pk).status == Grant.Status.PENDING

    call_command("chain_status")
    out, err = capsys.readouterr()
    assert "chain identity: reset" in out
    assert "sending is stopped" in err
    page = admin_client.get(reverse("admin:chain-status"))
    assert b"chain reset: the node is chain id" in page.content


def test_chain_status_on_a_reset_development_chain(deployed, fresh_chain, capsys):
    fresh_chain()
    call_command("chain_status")
    out, err = capsys.readouterr()
    assert "chain identity: reset" in out
    assert "re-created from the database" in err
