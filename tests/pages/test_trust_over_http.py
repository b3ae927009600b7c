"""The trust model's findings about pages, through a real socket (a live server and
`requests`, the whole middleware stack as a browser meets it): the operator cannot set an
owner's password (F2), sign-up is throttled per address (F3), hostile content is no 500 (F7),
and pages are throttled per user (F8)."""

import re
from datetime import timedelta

import pytest
import requests
from django.contrib.auth import get_user_model

from accounts.models import AccountEvent, Owner
from accounts.services.keys import sm4_key_generate
from tests.pages.conftest import encrypted_key, odometry
from tests.support.robot_setup import TEST_PASSWORD

pytestmark = pytest.mark.django_db(transaction=True)

OPERATOR_PASSWORD = "operator-Pass-4471"


def _csrf(page: requests.Response) -> str:
    return re.search(r'name="csrfmiddlewaretoken" value="([^"]+)"', page.text).group(1)


def _signed_in(
    base: str, username: str, password: str, *, path: str = "/login/"
) -> requests.Session:
    browser = requests.Session()
    form = browser.get(f"{base}{path}", timeout=30)
    answer = browser.post(
        f"{base}{path}",
        data={
            "username": username,
            "password": password,
            "csrfmiddlewaretoken": _csrf(form),
            "next": "/admin/" if path.startswith("/admin/") else "/dashboard/",
        },
        headers={"Referer": f"{base}{path}"},
        timeout=30,
    )
    assert answer.status_code == 200, answer.text[:200]
    return browser


def test_the_operator_cannot_set_an_owners_password_over_http(live_server, make_owner):
    owner = make_owner("alice")
    get_user_model().objects.create_superuser("op", password=OPERATOR_PASSWORD)
    before = Owner.objects.get(pk=owner.pk).user.password
    admin = _signed_in(live_server.url, "op", OPERATOR_PASSWORD, path="/admin/login/")
    url = f"{live_server.url}/admin/auth/user/{owner.user_id}/password/"
    assert admin.get(url, timeout=30).status_code == 403
    change = admin.get(f"{live_server.url}/admin/auth/user/{owner.user_id}/change/", timeout=30)
    attempt = admin.post(
        url,
        data={
            "password1": "Hijacked-9921",
            "password2": "Hijacked-9921",
            "csrfmiddlewaretoken": _csrf(change),
        },
        headers={"Referer": url},
        timeout=30,
    )
    assert attempt.status_code == 403
    assert Owner.objects.get(pk=owner.pk).user.password == before
    # The operator's session opens no owner page, and the owner's own password still works.
    assert admin.get(f"{live_server.url}/records/", timeout=30).status_code == 403
    mine = _signed_in(live_server.url, "alice", TEST_PASSWORD)
    security = mine.get(f"{live_server.url}/account/security/", timeout=30)
    assert "tried to set your password" in security.text
    assert AccountEvent.objects.filter(owner=owner, actor__username="op").count() == 1


def test_sign_up_is_throttled_per_address_over_http(live_server, deployed, settings):
    settings.SIGNUP_RATE_PER_ADDRESS = "2/hour"

    def register(username: str) -> requests.Response:
        browser = requests.Session()
        form = browser.get(f"{live_server.url}/register/", timeout=30)
        return browser.post(
            f"{live_server.url}/register/",
            data={
                "username": username,
                "password1": TEST_PASSWORD,
                "password2": TEST_PASSWORD,
                "key_ciphertext": encrypted_key(sm4_key_generate()),
                "csrfmiddlewaretoken": _csrf(form),
            },
            headers={"Referer": f"{live_server.url}/register/"},
            allow_redirects=False,
            timeout=30,
        )

    assert register("ann").status_code == 302
    assert register("ben").status_code == 302
    refused = register("cid")
    assert refused.status_code == 429
    assert int(refused.headers["Retry-After"]) > 0
    assert not get_user_model().objects.filter(username="cid").exists()


def test_hostile_odometry_is_no_500_and_pages_are_throttled_over_http(
    live_server, make_robot, upload, settings
):
    setup = make_robot("alice")
    upload(setup, 1, plaintext=odometry("alice", 1.0, 2.0))
    hostile = odometry("alice", 0.0, 0.0).replace(b'"x":0.0', b'"x":' + b"9" * 400, 1)
    hostile = hostile.replace(b'"y":0.0', b'"y":1e999', 1)
    bad = upload(setup, 2, plaintext=hostile)
    later = upload(setup, 3, plaintext=odometry("alice", 3.0, 4.0))
    browser = _signed_in(live_server.url, "alice", TEST_PASSWORD)
    page = browser.get(f"{live_server.url}/records/{bad.pk}/", timeout=60)
    assert page.status_code == 200
    assert "could not be interpreted" in page.text
    around = {
        "robot": str(later.robot_id),
        "topic": later.topic,
        "fields": "position.x,position.y",
        "since": (later.captured_at - timedelta(minutes=1)).isoformat(),
        "until": (later.captured_at + timedelta(minutes=1)).isoformat(),
    }
    series = browser.get(f"{live_server.url}/api/v1/records/series/", params=around, timeout=60)
    assert series.status_code == 200
    assert series.json()["without_values"] == 1  # the hostile record: no value read from it
    # The records a user's pages have checked are limited per user (what is left of a day's
    # budget of 2: the bucket keeps no more than its new size).
    settings.CHECK_BUDGET = "2/day"
    answers = [
        browser.get(f"{live_server.url}/records/{later.pk}/", timeout=60).status_code
        for _ in range(3)
    ]
    assert answers[-1] == 429
