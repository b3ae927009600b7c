"""Where webhooks may not go (issue 37.4): every IPv6 spelling of an inner IPv4 address, the
site-local and transition prefixes, ports other than 80 and 443, user info and fragments;
refused when the URL is added and again at delivery, when the name now resolves elsewhere.
The resolver is replaced at the socket boundary (socket.getaddrinfo): the names are the test's."""

import socket

import pytest

from accounts.services.owners import owner_create
from alerts.errors import WebhookUrlRefused
from alerts.models import AlertDelivery, AlertKind
from alerts.services import alert_test_send, webhook_endpoint_create
from alerts.webhooks import globally_routable, webhook_url_check
from smcrypto import sm4
from tests.support.robot_setup import TEST_PASSWORD

# Each accepted before issue 37 (the audit's list), plus the other transition forms.
INNER_SPELLINGS = [
    "::127.0.0.1",  # IPv4-compatible loopback
    "::7f00:1",
    "::a9fe:a9fe",  # the metadata service, IPv4-compatible
    "::a00:1",
    "::8.8.8.8",  # IPv4-compatible is deprecated whatever it embeds
    "::ffff:127.0.0.1",  # mapped
    "::ffff:0:7f00:1",  # SIIT translated
    "64:ff9b::7f00:1",  # NAT64 well-known prefix, inner IPv4
    "64:ff9b::a9fe:a9fe",
    "64:ff9b::a00:1",
    "64:ff9b:1::808:808",  # NAT64 local-use prefix
    "2002:7f00:1::1",  # 6to4
    "2002:808:808::1",
    "2001:0:4136:e378:8000:63bf:3fff:fdd2",  # Teredo
    "fec0::1",  # site-local
    "fe80::1",
    "fd00::1",
    "::1",
    "127.0.0.1",
    "169.254.169.254",
    "100.64.0.1",
]
PUBLIC = ["8.8.8.8", "2001:4860:4860::8888", "64:ff9b::808:808", "::ffff:8.8.8.8"]
HOST = "hooks.example.test"


@pytest.fixture
def dns(monkeypatch):
    """`dns.answer` is what HOST resolves to; every other name resolves as before."""
    real = socket.getaddrinfo

    class Answer:
        answer = "8.8.8.8"

    def getaddrinfo(host, port, *args, **kwargs):
        if host != HOST:
            return real(host, port, *args, **kwargs)
        family = socket.AF_INET6 if ":" in Answer.answer else socket.AF_INET
        return [(family, socket.SOCK_STREAM, 6, "", (Answer.answer, port))]

    monkeypatch.setattr(socket, "getaddrinfo", getaddrinfo)
    return Answer


@pytest.mark.nodb
def test_every_inner_spelling_is_refused_written_and_resolved(settings, dns):
    settings.ALERTS_WEBHOOK_ALLOW_PRIVATE = False
    assert [a for a in INNER_SPELLINGS if globally_routable(a)] == []
    assert [a for a in PUBLIC if not globally_routable(a)] == []
    for address in INNER_SPELLINGS:
        literal = f"[{address}]" if ":" in address else address
        with pytest.raises(WebhookUrlRefused, match="globally routable"):
            webhook_url_check(f"http://{literal}/hook")
        dns.answer = address
        with pytest.raises(WebhookUrlRefused, match="globally routable"):
            webhook_url_check(f"https://{HOST}/hook")
    for address in PUBLIC:
        dns.answer = address
        assert webhook_url_check(f"https://{HOST}/hook").address == address


@pytest.mark.nodb
def test_ports_userinfo_and_fragments(settings, dns):
    settings.ALERTS_WEBHOOK_ALLOW_PRIVATE = False
    settings.ALERTS_WEBHOOK_PORTS = []
    for url in (
        f"https://{HOST}:22/hook",
        f"http://{HOST}:6379/",
        f"http://{HOST}:0/",
        f"https://{HOST}:8443/hook",
    ):
        with pytest.raises(WebhookUrlRefused, match="port"):
            webhook_url_check(url)
    for url in (f"https://{HOST}/hook#@127.0.0.1", f"https://{HOST}/#"):
        with pytest.raises(WebhookUrlRefused, match="fragment"):
            webhook_url_check(url)
    for url in (f"https://user@{HOST}/hook", f"https://:pw@{HOST}/", f"https://@{HOST}/"):
        with pytest.raises(WebhookUrlRefused, match="user name"):
            webhook_url_check(url)
    assert webhook_url_check(f"http://{HOST}:80/h").port == 80
    assert webhook_url_check(f"https://{HOST}:443/h").port == 443
    settings.ALERTS_WEBHOOK_PORTS = [8443]  # the operator allows one more
    assert webhook_url_check(f"https://{HOST}:8443/h").port == 8443


@pytest.mark.parametrize("inner", ["::7f00:1", "64:ff9b::a9fe:a9fe", "fec0::1"])
def test_a_name_that_turns_inner_is_refused_at_delivery(
    db, settings, dns, alerts_on, django_capture_on_commit_callbacks, inner
):
    settings.ALERTS_WEBHOOK_ALLOW_PRIVATE = False
    owner = owner_create(username="dora", password=TEST_PASSWORD, sm4_key=sm4.generate_key())
    dns.answer = "8.8.8.8"
    webhook_endpoint_create(owner=owner, url=f"https://{HOST}/hook")
    alerts_on(owner, email=[], webhook=[AlertKind.GRANT_REVOKED])
    dns.answer = inner  # the name now points inside
    with django_capture_on_commit_callbacks(execute=True):
        alert_test_send(owner=owner)
    delivery = AlertDelivery.objects.get(channel=AlertDelivery.Channel.WEBHOOK)
    assert delivery.status == AlertDelivery.Status.FAILED
    assert "globally routable" in delivery.last_error
    assert inner in delivery.last_error
    assert delivery.response_status is None  # nothing was sent


@pytest.mark.nodb
def test_the_operator_may_allow_inner_addresses(settings, dns):
    settings.ALERTS_WEBHOOK_ALLOW_PRIVATE = True
    dns.answer = "::7f00:1"
    assert webhook_url_check(f"https://{HOST}/hook").address == "::7f00:1"
