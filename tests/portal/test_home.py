"""The front page only sends visitors on: to sign in, to their dashboard, or to the admin.

Anonymous visitors learn nothing of the deployment there, and their visit costs no chain call.
"""

import threading
from collections.abc import Iterator
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from io import StringIO

import pytest
from django.contrib.auth import get_user_model
from django.core.management import call_command
from django.urls import reverse

from accounts.services.owners import owner_create
from chainworker.models import Deployment
from smcrypto import sm4
from tests.support.robot_setup import TEST_PASSWORD

pytestmark = pytest.mark.django_db


@pytest.fixture
def counting_node(settings) -> Iterator[list[str]]:
    """The chain node is an HTTP server that only counts the requests made to it."""
    hits: list[str] = []

    class Handler(BaseHTTPRequestHandler):
        def do_POST(self) -> None:
            hits.append(self.path)
            self.send_response(503)
            self.end_headers()

        def log_message(self, *args: object) -> None:
            pass

    server = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    settings.CHAIN_RPC_URL = f"http://127.0.0.1:{server.server_address[1]}"
    try:
        yield hits
    finally:
        server.shutdown()
        server.server_close()


def test_anonymous_visitor_is_sent_to_sign_in_without_a_chain_call(client, counting_node):
    page = client.get("/")
    assert page.status_code == 302
    assert page["Location"] == reverse("login")
    assert client.get(page["Location"]).status_code == 200
    assert counting_node == []


def test_anonymous_visitor_sees_no_chain_internals(client, settings):
    call_command("chain_deploy", stdout=StringIO())
    address = Deployment.objects.get(is_active=True).address
    html = client.get("/", follow=True).content.decode()
    assert 'id="login-form"' in html
    assert reverse("register") in html
    for internal in (address, settings.CHAIN_RPC_URL, "Chain id", "Latest block", "anvil/"):
        assert internal not in html


def test_owner_goes_to_the_dashboard(client):
    owner = owner_create(username="olga", password=TEST_PASSWORD, sm4_key=sm4.generate_key())
    client.force_login(owner.user)
    page = client.get("/")
    assert page.status_code == 302
    assert page["Location"] == reverse("dashboard")
    assert client.get(page["Location"]).status_code == 200


def test_operator_goes_to_the_admin_console(client):
    operator = get_user_model().objects.create_superuser("root", password=TEST_PASSWORD)
    client.force_login(operator)
    page = client.get("/")
    assert page.status_code == 302
    assert page["Location"] == reverse("admin:index")
