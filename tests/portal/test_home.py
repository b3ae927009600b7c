"""The front page shows what is running."""

from io import StringIO

import pytest
from django.core.management import call_command

from chainworker.models import Deployment
from tests.anvil import free_port

pytestmark = pytest.mark.django_db


def test_home_shows_the_deployed_contract(client):
    call_command("chain_deploy", stdout=StringIO())
    address = Deployment.objects.get(is_active=True).address
    page = client.get("/")
    assert page.status_code == 200
    assert address in page.content.decode()


def test_home_says_when_the_contract_is_missing(client):
    page = client.get("/")
    assert page.status_code == 200
    assert "chain_deploy" in page.content.decode()


def test_home_says_when_the_chain_is_down(client, settings):
    settings.CHAIN_RPC_URL = f"http://127.0.0.1:{free_port()}"
    page = client.get("/")
    assert page.status_code == 200
    assert "not reachable" in page.content.decode()
