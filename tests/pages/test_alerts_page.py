"""The alerts page: an owner's choices saved, bad input answered with form errors (never a
500) and nothing changed, each webhook secret shown once, and another owner's webhooks neither
shown nor deletable."""

import re

import pytest
from django.core import mail
from django.urls import reverse

from alerts.models import AlertDelivery, AlertPreferences, WebhookEndpoint
from alerts.services import webhook_endpoint_create

pytestmark = pytest.mark.django_db

ALERTS = reverse("alerts")
WEBHOOKS = reverse("alert-webhook-create")
GOOD = {
    "email": "alice@example.org",
    "email_kinds": ["record_tampered", "robot_silent"],
    "webhook_kinds": ["gas_low"],
    "robot_silent_minutes": "30",
    "gas_low_below_ether": "0.05",
}


def _confirm_link(message) -> str:
    return re.search(r"http://testserver(/account/alerts/verify/\S+/)", message.body).group(1)


def test_choices_are_saved_and_shown_again(login, pending_owner):
    alice = pending_owner("alice")
    client = login(alice)
    page = client.get(ALERTS)
    assert page.status_code == 200
    assert b'data-testid="nav-alerts"' in page.content
    assert client.post(ALERTS, GOOD).status_code == 302
    saved = AlertPreferences.objects.get(owner=alice)
    assert saved.email == "alice@example.org"
    assert saved.email_kinds == ["record_tampered", "robot_silent"]
    assert saved.webhook_kinds == ["gas_low"]
    assert saved.robot_silent_minutes == 30
    assert saved.gas_low_below_wei == 5 * 10**16
    html = client.get(ALERTS).content.decode()
    assert 'value="0.05"' in html
    assert 'data-testid="email-record_tampered" checked' in html
    assert 'data-testid="webhook-record_tampered">' in html  # not chosen: not checked


BAD_CHOICES = [
    ({"email": ""}, "email"),  # e-mail alerts chosen, no address
    ({"email": "not an address"}, "email"),
    ({"email_kinds": ["no_such_event"]}, "email_kinds"),
    ({"robot_silent_minutes": ""}, "robot_silent_minutes"),  # silent robots chosen
    ({"robot_silent_minutes": "1"}, "robot_silent_minutes"),
    ({"robot_silent_minutes": "ten"}, "robot_silent_minutes"),
    ({"robot_silent_minutes": "9" * 30}, "robot_silent_minutes"),
    ({"gas_low_below_ether": "-1"}, "gas_low_below_ether"),
    ({"gas_low_below_ether": ""}, "gas_low_below_ether"),  # low gas chosen
    ({"gas_low_below_ether": "1e400"}, "gas_low_below_ether"),
    ({"gas_low_below_ether": "NaN"}, "gas_low_below_ether"),
]
REFUSED_URLS = [
    "http://127.0.0.1:8000/hook",
    "http://[::7f00:1]/hook",
    "http://[64:ff9b::a9fe:a9fe]/",
    "https://example.org:22/hook",
    "https://example.org/hook#@127.0.0.1",
    "http://169.254.169.254/",
    "not a url",
    "ftp://x.org/",
    "",
    "http://" + "a" * 600 + ".org/",
]


def test_bad_input_is_a_form_error_and_changes_nothing(login, pending_owner, settings):
    settings.ALERTS_WEBHOOK_ALLOW_PRIVATE = False
    alice = pending_owner("alice")
    client = login(alice)
    for change, field in BAD_CHOICES:
        page = client.post(ALERTS, {**GOOD, **change})
        assert page.status_code == 400, change
        assert field in page.context["form"].errors, change
        assert b'class="errorlist' in page.content
    assert not AlertPreferences.objects.filter(owner=alice).exists()
    for url in REFUSED_URLS:
        page = client.post(WEBHOOKS, {"url": url})
        assert page.status_code == 400, url
        assert "url" in page.context["webhook_form"].errors, url
    assert not WebhookEndpoint.objects.exists()


def test_a_webhook_secret_is_shown_once(login, pending_owner, settings):
    settings.ALERTS_WEBHOOK_ALLOW_PRIVATE = True
    settings.ALERTS_WEBHOOK_PORTS = [9]  # the receivers below listen on port 9
    client = login(pending_owner("alice"))
    page = client.post(WEBHOOKS, {"url": "http://127.0.0.1:9/hook"})
    assert page.status_code == 201
    assert "no-store" in page["Cache-Control"]
    secret = page.context["secret"]
    assert secret.encode() in page.content
    listing = client.get(ALERTS).content.decode()
    assert "http://127.0.0.1:9/hook" in listing
    assert secret not in listing
    assert secret[:10] in listing  # its first characters tell secrets apart


def test_another_owners_webhooks_are_invisible_and_untouchable(login, pending_owner, settings):
    settings.ALERTS_WEBHOOK_ALLOW_PRIVATE = True
    settings.ALERTS_WEBHOOK_PORTS = [9]  # the receivers below listen on port 9
    alice, mallory = pending_owner("alice"), pending_owner("mallory")
    endpoint, _secret = webhook_endpoint_create(owner=alice, url="http://127.0.0.1:9/alice")
    client = login(mallory)
    assert b"/alice" not in client.get(ALERTS).content
    delete = reverse("alert-webhook-delete", args=[endpoint.pk])
    assert client.post(delete).status_code == 404
    assert WebhookEndpoint.objects.filter(pk=endpoint.pk).exists()
    client = login(alice)
    assert client.post(delete).status_code == 302
    assert not WebhookEndpoint.objects.exists()


def test_an_address_is_used_once_confirmed_by_its_link(
    login, pending_owner, django_capture_on_commit_callbacks
):
    alice, mallory = pending_owner("alice"), pending_owner("mallory")
    client = login(alice)
    with django_capture_on_commit_callbacks(execute=True):
        page = client.post(ALERTS, GOOD, follow=True)
    assert b"We sent a link to alice@example.org" in page.content
    [sent] = mail.outbox
    assert sent.to == ["alice@example.org"]
    link = _confirm_link(sent)
    state = re.search(r'data-testid="email-state">(.*?)</p>', page.content.decode()).group(1)
    assert "not confirmed</span> We sent a link to alice@example.org: open it to confirm" in state
    assert "Until you do, no alert is e-mailed to it." in state
    assert not AlertPreferences.objects.get(owner=alice).email_verified_at
    # Not for another account, nor with a changed token: refused, nothing confirmed.
    assert b"not confirmed" in login(mallory).get(link, follow=True).content
    assert b"not confirmed" in login(alice).get(link[:-3] + "x/", follow=True).content
    assert not AlertPreferences.objects.get(owner=alice).email_verified_at
    page = client.get(link, follow=True)
    assert b"alice@example.org is confirmed" in page.content
    assert AlertPreferences.objects.get(owner=alice).email_verified_at
    # Saving the same address keeps it confirmed; another one needs its own link.
    client.post(ALERTS, GOOD)
    assert AlertPreferences.objects.get(owner=alice).email_verified_at
    client.post(ALERTS, {**GOOD, "email": "alice@elsewhere.example"})
    assert not AlertPreferences.objects.get(owner=alice).email_verified_at
    assert b"not confirmed" in client.get(link, follow=True).content  # the old address's link


def test_the_test_alert_is_logged_for_its_owner_only(
    login, pending_owner, django_capture_on_commit_callbacks
):
    alice, bob = pending_owner("alice"), pending_owner("bob")
    client = login(alice)
    with django_capture_on_commit_callbacks(execute=True):
        client.post(ALERTS, {**GOOD, "email_kinds": [], "webhook_kinds": []})
    client.get(_confirm_link(mail.outbox[0]))
    with django_capture_on_commit_callbacks(execute=True):
        sent = client.post(reverse("alert-test"), follow=True)
    assert "A test alert is on its way to 1 channel." in sent.content.decode()  # not "(s)"
    delivery = AlertDelivery.objects.get()
    assert (delivery.target, delivery.status) == ("alice@example.org", AlertDelivery.Status.SENT)
    assert b'data-testid="alert-delivery"' in client.get(ALERTS).content
    assert b'data-testid="alert-delivery"' not in login(bob).get(ALERTS).content


def test_a_test_alert_with_nowhere_to_go_says_so(login, pending_owner):
    """Nothing set up: the page says a test alert would reach nothing, and sending one says
    why nothing was sent (issue 48); an address not confirmed yet is named."""
    client = login(pending_owner("alice"))
    page = client.get(ALERTS).content.decode()
    assert 'data-testid="alert-test-nowhere"' in page
    answer = client.post(reverse("alert-test"), follow=True).content.decode()
    assert "Nothing was sent: no e-mail address and no webhook is set up" in answer
    assert not AlertDelivery.objects.exists()
    assert client.post(ALERTS, GOOD).status_code == 302
    answer = client.post(reverse("alert-test"), follow=True).content.decode()
    assert "Nothing was sent: alice@example.org is not confirmed yet" in answer
