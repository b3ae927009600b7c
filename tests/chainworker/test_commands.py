"""`manage.py chain_deploy` and `manage.py chain_status`."""

import json
import os
import subprocess
import sys
from io import StringIO
from pathlib import Path

import pytest
from django.core.management import CommandError, call_command
from django.db import connection
from django.test.utils import CaptureQueriesContext
from eth_account import Account

from chainworker import services as chain_services
from chainworker.models import Deployment
from chainworker.services import chain_client, operator_account
from stack.anvil import free_port, start_anvil

REPO_ROOT = Path(__file__).resolve().parents[2]
pytestmark = pytest.mark.django_db


def _deploy(*args: str) -> dict:
    out = StringIO()
    call_command("chain_deploy", "--json", *args, stdout=out)
    return json.loads(out.getvalue())


def test_deploy_is_idempotent_and_force_retires_the_old_one():
    first = _deploy()
    assert first["created"] is True
    assert first["reason"] == "first deployment"
    again = _deploy()
    assert again["created"] is False
    assert again["address"] == first["address"]
    assert Deployment.objects.count() == 1

    forced = _deploy("--force")
    assert forced["created"] is True
    assert forced["address"] != first["address"]
    active = Deployment.objects.get(is_active=True)
    assert active.address == forced["address"]
    assert Deployment.objects.get(address=first["address"]).is_active is False
    assert chain_client().address == forced["address"]


def test_deploy_again_when_the_recorded_contract_is_gone():
    first = _deploy()
    Deployment.objects.filter(address=first["address"]).update(address=Account.create().address)
    redeployed = _deploy()
    assert redeployed["created"] is True
    assert "no code at recorded address" in redeployed["reason"]
    assert Deployment.objects.filter(is_active=True).count() == 1


def test_the_active_deployment_is_read_once_per_recheck_interval(monkeypatch):
    """chain_client() does not ask the database for the deployment on every call; a contract
    another process deployed is followed once DEPLOYMENT_RECHECK_SECONDS have passed."""
    first = _deploy()
    chain_services._clients.clear()  # a fresh process
    with CaptureQueriesContext(connection) as queries:
        for _ in range(5):
            assert chain_client().address == first["address"]
    assert len([q for q in queries if "chainworker_deployment" in q["sql"]]) == 1

    # Another process deploys: the row changes under this one.
    client = chain_client()
    client.deploy(operator_account())
    other = client.address
    client.use_contract(first["address"])  # what this process still uses
    Deployment.objects.filter(is_active=True).update(is_active=False)
    Deployment.objects.create(
        chain_id=chain_client().chain_id,
        genesis_hash=chain_client().genesis_hash,
        address=other,
        tx_hash="0x" + "00" * 32,
        block_number=1,
        deployer=operator_account().address,
    )
    assert chain_client().address == first["address"]  # within the interval: as read
    monkeypatch.setattr(chain_services, "DEPLOYMENT_RECHECK_SECONDS", 0)
    assert chain_client().address == other


def test_status_shows_node_contract_admin_and_operator(operator):
    deployed = _deploy()
    out = StringIO()
    call_command("chain_status", stdout=out)
    text = out.getvalue()
    assert deployed["address"] in text
    assert operator.address in text
    assert "chain id" in text

    out = StringIO()
    call_command("chain_status", "--json", stdout=out)
    status = json.loads(out.getvalue())
    assert status["contract_address"] == deployed["address"]
    assert status["admin"] == operator.address
    assert status["operator_balance_wei"] > 0
    assert status["latest_block"] >= deployed["block_number"]


def test_status_before_deployment_says_what_to_do():
    err = StringIO()
    call_command("chain_status", stdout=StringIO(), stderr=err)
    assert "chain_deploy" in err.getvalue()


def test_commands_fail_cleanly_when_the_node_is_down(settings):
    settings.CHAIN_RPC_URL = f"http://127.0.0.1:{free_port()}"
    with pytest.raises(CommandError, match="chain unavailable"):
        call_command("chain_status", stdout=StringIO())
    with pytest.raises(CommandError, match="deployment failed"):
        call_command("chain_deploy", stdout=StringIO())


@pytest.mark.process
def test_command_line_against_anvil(tmp_path):
    """The real CLI, as an operator runs it, against a real node, in fresh processes."""
    with start_anvil() as node:
        env = {
            **os.environ,
            "CHAIN_RPC_URL": node.url,
            "AUTHROS_VAR_DIR": str(tmp_path),
            "DATABASE_URL": f"sqlite:///{tmp_path / 'db.sqlite3'}",
        }

        def manage(*args: str) -> str:
            done = subprocess.run(
                [sys.executable, "manage.py", *args],
                cwd=REPO_ROOT,
                env=env,
                capture_output=True,
                text=True,
                timeout=120,
                check=False,
            )
            assert done.returncode == 0, done.stderr
            return done.stdout

        manage("migrate", "--noinput")
        first = json.loads(manage("chain_deploy", "--json"))
        second = json.loads(manage("chain_deploy", "--json"))
        assert first["created"]
        assert not second["created"]
        assert second["address"] == first["address"]
        status = json.loads(manage("chain_status", "--json"))
        assert status["contract_address"] == first["address"]
        assert status["client_version"].lower().startswith("anvil")
        assert (tmp_path / "secrets" / "operator.key").stat().st_mode & 0o777 == 0o600
