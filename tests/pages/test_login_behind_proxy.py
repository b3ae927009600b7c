"""Sign-in lockout behind a reverse proxy: failures count per client, not per proxy.

django-axes takes the client's address the way the API throttles do, from API_NUM_PROXIES
(REST_FRAMEWORK NUM_PROXIES): 0 trusts no header, N takes the X-Forwarded-For entry that
the N-th proxy from the portal appended. The test client's peer address (127.0.0.1) stands
for the proxy.
"""

import pytest
from axes.models import AccessAttempt
from django.urls import reverse

from tests.support.robot_setup import TEST_PASSWORD

pytestmark = pytest.mark.django_db

ATTACKER = "203.0.113.7"
OWNER_AT_HOME = "198.51.100.9"


@pytest.fixture
def proxies(settings):
    def set_count(count: int) -> None:
        settings.REST_FRAMEWORK = {**settings.REST_FRAMEWORK, "NUM_PROXIES": count}

    return set_count


def _sign_in(client, password: str, forwarded_for: str) -> int:
    form = {"username": "erin", "password": password}
    return client.post(reverse("login"), form, HTTP_X_FORWARDED_FOR=forwarded_for).status_code


def _lock_out_from(client, settings, address: str) -> None:
    for _ in range(settings.AXES_FAILURE_LIMIT - 1):
        assert _sign_in(client, "guess", address) == 400
    assert _sign_in(client, "guess", address) == 429


def test_behind_one_proxy_each_client_address_is_counted_apart(
    client, pending_owner, settings, proxies
):
    proxies(1)
    pending_owner("erin")
    _lock_out_from(client, settings, ATTACKER)
    assert AccessAttempt.objects.get(username="erin").ip_address == ATTACKER

    # The attacker is locked out even with the right password, and cannot claim another
    # address: the proxy appends the real one after whatever the client sent.
    assert _sign_in(client, TEST_PASSWORD, ATTACKER) == 429
    assert _sign_in(client, TEST_PASSWORD, f"{OWNER_AT_HOME}, {ATTACKER}") == 429
    # The owner, from another address, still signs in.
    assert _sign_in(client, TEST_PASSWORD, OWNER_AT_HOME) == 302
    assert client.get(reverse("dashboard")).status_code == 200


def test_without_proxies_the_header_is_ignored(client, pending_owner, settings, proxies):
    proxies(0)
    pending_owner("erin")
    _lock_out_from(client, settings, ATTACKER)
    assert AccessAttempt.objects.get(username="erin").ip_address == "127.0.0.1"
    # Another X-Forwarded-For changes nothing: the peer address is the one that counts.
    assert _sign_in(client, TEST_PASSWORD, OWNER_AT_HOME) == 429
    assert client.get(reverse("dashboard")).status_code == 302
