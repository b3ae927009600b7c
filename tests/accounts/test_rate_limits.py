"""The API's rate limits count in Redis by a sliding window: this window's requests plus the
last window's, weighted by how much of it overlaps the last `duration` seconds."""

import pytest
from rest_framework.request import Request
from rest_framework.test import APIRequestFactory

from accounts.authentication import AnonRateThrottle
from core.redis_client import get_redis, redis_key

pytestmark = pytest.mark.django_db


@pytest.fixture
def four_a_minute(settings):
    settings.REST_FRAMEWORK = {
        **settings.REST_FRAMEWORK,
        "DEFAULT_THROTTLE_RATES": {
            **settings.REST_FRAMEWORK["DEFAULT_THROTTLE_RATES"],
            "anon": "4/minute",
        },
    }


def _allowed_at(now: float, address: str = "203.0.113.9") -> tuple[bool, float | None]:
    request = Request(APIRequestFactory().get("/api/v1/sm2-public-key/", REMOTE_ADDR=address))
    throttle = AnonRateThrottle()
    throttle.timer = lambda: now
    return throttle.allow_request(request, view=None), throttle.wait()


@pytest.mark.usefixtures("four_a_minute")
def test_a_window_allows_its_rate_then_refuses_until_it_slides_past():
    start = 6000.0  # a window boundary (100 minutes)
    assert [_allowed_at(start + t)[0] for t in (0, 1, 2, 3)] == [True] * 4
    allowed, wait = _allowed_at(start + 10)  # the 5th: refused, and counted
    assert allowed is False
    assert wait == 50  # until this window ends
    # Just into the next window the last one still weighs almost whole: refused.
    assert _allowed_at(start + 61)[0] is False
    # Three quarters into it: a quarter of the last window's 5 (1.25) and this window's 2.
    assert _allowed_at(start + 105)[0] is True
    assert _allowed_at(start + 106)[0] is False  # 14/60 of 5 (1.17) and 3: above 4
    # Another client has its own count.
    assert _allowed_at(start + 107, address="198.51.100.7")[0] is True


@pytest.mark.usefixtures("four_a_minute")
def test_counts_expire_and_stay_in_the_portals_namespace():
    _allowed_at(6000.0)
    keys = list(get_redis().scan_iter(redis_key("throttle", "anon", "*")))
    assert len(keys) == 1
    assert 0 < get_redis().ttl(keys[0]) <= 121


def test_without_redis_the_limit_is_not_checked(monkeypatch, four_a_minute):
    from redis.exceptions import ConnectionError as RedisDown

    import accounts.authentication as authentication

    def down():
        raise RedisDown("gone")

    monkeypatch.setattr(authentication, "get_redis", down)
    assert all(_allowed_at(6000.0 + t)[0] for t in range(10))
