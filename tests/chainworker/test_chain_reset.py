"""Chain reset detection: the node compared with the active deployment, and what the portal
does on a real network (stops sending and tells the operator)."""

import json
import logging

import pytest
from django.core.management import call_command
from django.urls import reverse

from accounts.services.funding import owner_top_up
from chainworker import services as chain_services
from chainworker.models import Deployment
from chainworker.work import ChainWorkNotReady
from core.redis_client import get_redis
from sharing.models import Grant, Record
from sharing.services import anchoring
from sharing.services.grant_chain import grant_sync_on_chain
from sharing.services.grants import grant_create
from sharing.services.reconcile import chain_reconcile
from sharing.services.uploads import record_create
from tests.support.logs import logged_by

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

    with logged_by("sharing.services.reconcile") as seen:
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


def _verdict_keep(state: str, chain: str) -> None:
    """A verdict of chain_work_check as another process keeps it in Redis."""
    get_redis().set(
        chain_services._identity_cache_key(),
        json.dumps({"state": state, "reason": "", "chain": chain}),
        ex=60,
    )


def test_a_kept_verdict_for_this_process_chain_costs_no_chain_look_up(deployed, monkeypatch):
    _verdict_keep("same", f"{deployed.chain_id}:{deployed.genesis_hash}")
    monkeypatch.setattr(
        chain_services, "chain_identity", lambda: pytest.fail("the node was asked again")
    )

    chain_services.chain_work_check()


def test_a_process_whose_client_predates_a_reset_follows_the_chain_another_process_checked(
    deployed,
):
    """Another process found the reset, deployed again and kept "same" for the new chain: a
    process whose client was built before the reset must not send with it (its nonce counters
    are the old chain's: a nonce above the account's waits in the new node's pool for ever)."""
    node = f"{deployed.chain_id}:{deployed.genesis_hash}"
    deployed.__dict__["genesis_hash"] = "0x" + "ab" * 32  # built for the chain before the reset
    _verdict_keep("same", node)

    chain_services.chain_work_check()

    client = chain_services.chain_client()
    assert client is not deployed
    assert f"{client.chain_id}:{client.genesis_hash}" == node
    assert json.loads(get_redis().get(chain_services._identity_cache_key()))["chain"] == node


def test_a_kept_reset_verdict_for_another_chain_is_checked_again(deployed):
    """A "reset" kept for a chain this process's client is not on is not taken on trust."""
    _verdict_keep("reset", f"{deployed.chain_id}:0x{'cd' * 32}")

    chain_services.chain_work_check()  # the node is the deployment's chain: no refusal
