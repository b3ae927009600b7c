"""Every model of the portal's apps is in the admin console, and read-only where the trust model
says so (docs/security.md, "The operator"): an operator adds, changes and deletes nothing here,
so cannot make the portal call a record genuine (records, roots, verdicts, the deployment
checked against) or widen a grant (grants and their changes). The few actions (re-anchor,
re-verify, revoke a robot's token, approve sign-ups) go through the services.
"""

import pytest
from django.apps import apps
from django.contrib import admin
from django.contrib.auth import get_user_model
from django.test import RequestFactory
from django.urls import reverse

from alerts.services import webhook_endpoint_create
from tests.support.robot_setup import TEST_PASSWORD

pytestmark = pytest.mark.django_db

OUR_APPS = ("accounts", "sharing", "alerts", "chainworker")
# Change permission only for their actions (the services do the work); every field read-only.
CHANGED_BY_ACTIONS_ONLY = {"sharing.Record", "accounts.Robot"}


def our_models() -> list:
    return [model for model in apps.get_models() if model._meta.app_label in OUR_APPS]


@pytest.fixture
def superuser():
    return get_user_model().objects.create_superuser("root", password=TEST_PASSWORD)


@pytest.fixture
def request_of(superuser):
    request = RequestFactory().get("/admin/")
    request.user = superuser
    return request


def test_every_model_of_our_apps_is_registered():
    missing = [model._meta.label for model in our_models() if not admin.site.is_registered(model)]
    assert missing == []


@pytest.mark.parametrize("label", [model._meta.label for model in our_models()])
def test_no_model_can_be_added_changed_or_deleted_in_the_console(label, request_of):
    model = apps.get_model(label)
    model_admin = admin.site._registry[model]
    assert model_admin.has_view_permission(request_of)
    assert not model_admin.has_add_permission(request_of)
    assert not model_admin.has_delete_permission(request_of)
    if label in CHANGED_BY_ACTIONS_ONLY:
        shown = set(model_admin.get_fields(request_of))
        assert shown <= set(model_admin.get_readonly_fields(request_of)), label
    else:
        assert not model_admin.has_change_permission(request_of), label


@pytest.mark.parametrize("label", [model._meta.label for model in our_models()])
def test_the_console_refuses_adds_and_deletes_and_changes_of_read_only_models(
    label, client, superuser
):
    client.force_login(superuser)
    opts = apps.get_model(label)._meta
    name = f"admin:{opts.app_label}_{opts.model_name}"
    assert client.get(reverse(f"{name}_add")).status_code == 403
    assert client.post(reverse(f"{name}_add"), {}).status_code == 403
    # The permission is asked before the row is looked up: no row is needed to be refused.
    assert client.post(reverse(f"{name}_delete", args=["1"]), {"post": "yes"}).status_code == 403
    if label not in CHANGED_BY_ACTIONS_ONLY:
        assert client.post(reverse(f"{name}_change", args=["1"]), {}).status_code == 403


def test_the_new_pages_never_show_a_token_or_a_webhook_secret(
    client, superuser, make_owner, make_owner_token, settings
):
    settings.ALERTS_WEBHOOK_ALLOW_PRIVATE = True  # the loopback resolves without a network
    alice = make_owner("alice")
    token, key = make_owner_token(alice)
    endpoint, secret = webhook_endpoint_create(owner=alice, url="https://127.0.0.1/hook")
    client.force_login(superuser)
    for model, obj in [("accounts_ownertoken", token), ("alerts_webhookendpoint", endpoint)]:
        for url in (
            reverse(f"admin:{model}_changelist"),
            reverse(f"admin:{model}_change", args=[obj.pk]),
        ):
            html = client.get(url).content.decode()
            assert token.token_prefix in html or endpoint.secret_prefix in html, url
            hidden = [key, token.token_hash, secret, bytes(endpoint.secret_wrapped).hex()]
            assert not [value for value in hidden if value in html], url
            assert "token_hash" not in html, url
            assert "secret_wrapped" not in html, url
