"""Delivery through real parts: an SMTP server (aiosmtpd) receives the e-mail, an HTTP
receiver checks the webhook's signature and sees the retry after answering 500 once."""

import hashlib
import hmac
import time

import pytest
from django.core import mail
from django.utils import timezone

from accounts.services.owners import owner_create
from alerts.errors import WebhookUrlRefused
from alerts.models import AlertDelivery, AlertKind
from alerts.services import (
    alert_test_send,
    deliveries_requeue_stale,
    grant_revoked_alert,
    webhook_endpoint_create,
)
from alerts.tasks import alerts_watch
from alerts.webhooks import webhook_url_check
from smcrypto import sm4
from tests.support.robot_setup import TEST_PASSWORD


@pytest.fixture
def owner(db):
    """An owner whose chain work is never run: delivery needs no chain."""
    return owner_create(username="carol", password=TEST_PASSWORD, sm4_key=sm4.generate_key())


def _verify(secret: str, headers: dict[str, str], body: bytes) -> bool:
    """What a receiver does (docs/alerts.md): recompute the HMAC, compare in constant time,
    and refuse a timestamp far from its own clock."""
    timestamp = headers["X-AuthROS-Timestamp"]
    if abs(time.time() - int(timestamp)) > 300:
        return False
    expected = hmac.new(secret.encode(), timestamp.encode() + b"." + body, hashlib.sha256)
    return hmac.compare_digest(headers["X-AuthROS-Signature"], "v1=" + expected.hexdigest())


def test_an_alert_reaches_a_real_smtp_server(
    owner, alerts_on, smtp_server, settings, django_capture_on_commit_callbacks
):
    settings.DEFAULT_FROM_EMAIL = "AuthROS <alerts@portal.example>"
    alerts_on(owner, email=[AlertKind.GRANT_REVOKED], address="carol@example.org")
    with django_capture_on_commit_callbacks(execute=True):
        grant_revoked_alert(grantee=owner, owner=owner)
    [message] = smtp_server.messages
    assert smtp_server.envelopes == [("alerts@portal.example", ["carol@example.org"])]
    assert message["Subject"] == "[AuthROS] Someone revoked your access"
    assert message["X-AuthROS-Event"] == "grant_revoked"
    assert "carol revoked your access" in message.get_payload(decode=True).decode()
    delivery = AlertDelivery.objects.get()
    assert (delivery.status, delivery.attempts) == (AlertDelivery.Status.SENT, 1)


def test_an_owner_who_chose_nothing_gets_nothing(owner, django_capture_on_commit_callbacks):
    with django_capture_on_commit_callbacks(execute=True):
        alert = grant_revoked_alert(grantee=owner, owner=owner)
    # The alert is kept, but no channel was chosen for it: nothing is sent.
    assert alert is not None
    assert not AlertDelivery.objects.exists()
    assert mail.outbox == []


def test_unreachable_mail_server_is_retried_then_failed(
    owner, alerts_on, settings, django_capture_on_commit_callbacks
):
    settings.EMAIL_BACKEND = "django.core.mail.backends.smtp.EmailBackend"
    settings.EMAIL_HOST, settings.EMAIL_PORT = "127.0.0.1", 9  # nothing listens (discard port)
    alerts_on(owner, email=[AlertKind.GRANT_REVOKED])
    with django_capture_on_commit_callbacks(execute=True):
        grant_revoked_alert(grantee=owner, owner=owner)
    delivery = AlertDelivery.objects.get()
    assert delivery.status == AlertDelivery.Status.FAILED
    assert delivery.attempts == settings.ALERTS_DELIVERY_MAX_RETRIES + 1
    assert "mail server" in delivery.last_error


def test_a_signed_webhook_is_retried_after_a_500(
    owner, alerts_on, webhook_receiver, django_capture_on_commit_callbacks
):
    endpoint, secret = webhook_endpoint_create(owner=owner, url=webhook_receiver.url)
    assert secret.startswith("whsec_")
    assert secret.encode() not in bytes(endpoint.secret_wrapped)
    alerts_on(owner, email=[], webhook=[AlertKind.GRANT_REVOKED])
    webhook_receiver.answers = [(500, {})]
    with django_capture_on_commit_callbacks(execute=True):
        alert = grant_revoked_alert(grantee=owner, owner=owner)
    first, second = webhook_receiver.received
    assert first.path == second.path == "/hooks/authros?x=1"
    for request in (first, second):
        assert _verify(secret, request.headers, request.body)
        assert not _verify(secret, request.headers, request.body.replace(b"carol", b"mallory"))
        assert not _verify("whsec_other", request.headers, request.body)
    delivery = AlertDelivery.objects.get()
    assert second.headers["X-AuthROS-Delivery"] == first.headers["X-AuthROS-Delivery"]
    assert second.headers["X-AuthROS-Delivery"] == str(delivery.pk)
    assert second.payload["type"] == "grant_revoked" == second.headers["X-AuthROS-Event"]
    assert second.payload["id"] == str(alert.pk)
    assert second.payload["owner"] == "carol"
    assert (delivery.status, delivery.attempts) == (AlertDelivery.Status.SENT, 2)
    assert delivery.response_status == 200


def test_a_redirect_is_not_followed_nor_retried(
    owner, alerts_on, webhook_receiver, django_capture_on_commit_callbacks
):
    webhook_endpoint_create(owner=owner, url=webhook_receiver.url)
    alerts_on(owner, email=[], webhook=[AlertKind.GRANT_REVOKED])
    webhook_receiver.answers = [(302, {"Location": webhook_receiver.url + "&again=1"})]
    with django_capture_on_commit_callbacks(execute=True):
        alert_test_send(owner=owner)
    assert len(webhook_receiver.received) == 1
    delivery = AlertDelivery.objects.get(channel=AlertDelivery.Channel.WEBHOOK)
    assert (delivery.status, delivery.response_status) == (AlertDelivery.Status.FAILED, 302)
    assert "redirect" in delivery.last_error


INNER_OR_BAD_URLS = [
    "http://127.0.0.1:8000/hook",
    "http://localhost/hook",
    "https://[::1]/hook",
    "http://10.1.2.3/hook",
    "http://192.168.0.10/hook",
    "http://172.16.5.4/hook",
    "http://169.254.169.254/latest/meta-data/",
    "http://100.64.0.1/hook",
    "http://[::ffff:127.0.0.1]/hook",
    "http://[fd00::1]/hook",
    "http://0.0.0.0/hook",
    "http://224.0.0.1/hook",
    "ftp://example.org/hook",
    "https://user:pw@example.org/hook",
    "https://no-such-host.invalid/hook",
    "http://example.org:99999/hook",
]


def _accepted(url: str) -> bool:
    try:
        webhook_url_check(url)
    except WebhookUrlRefused:
        return False
    return True


@pytest.mark.nodb
def test_inner_addresses_are_refused(settings):
    settings.ALERTS_WEBHOOK_ALLOW_PRIVATE = False
    assert [url for url in INNER_OR_BAD_URLS if _accepted(url)] == []
    settings.ALERTS_WEBHOOK_ALLOW_PRIVATE = True
    settings.ALERTS_WEBHOOK_PORTS = [8000]
    assert webhook_url_check("http://127.0.0.1:8000/h?a=b").target == "/h?a=b"


def test_a_lost_delivery_is_queued_again(
    owner, alerts_on, smtp_server, settings, django_capture_on_commit_callbacks
):
    alerts_on(owner, email=[AlertKind.GRANT_REVOKED])
    grant_revoked_alert(grantee=owner, owner=owner)  # its message is never sent (no commit)
    delivery = AlertDelivery.objects.get()
    assert deliveries_requeue_stale() == 0  # not stale yet
    AlertDelivery.objects.filter(pk=delivery.pk).update(
        updated_at=timezone.now() - timezone.timedelta(seconds=2 * 3600)
    )
    with django_capture_on_commit_callbacks(execute=True):
        watched = alerts_watch.apply().get()  # the beat task
    assert watched["deliveries_requeued"] == 1
    delivery.refresh_from_db()
    assert delivery.status == AlertDelivery.Status.SENT
    assert len(smtp_server.messages) == 1
