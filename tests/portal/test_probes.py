"""/healthz, /readyz and /metrics (portal/probes.py): what answers a load balancer and a
monitor, before any other middleware, never rate-limited, never in the access log."""

import socket

import pytest
from django.test import Client

from portal.scrape import state_collector
from stack.anvil import free_port
from tests.support.logs import logged_by

LOCAL = "127.0.0.1"
ELSEWHERE = "203.0.113.7"
TOKEN = "metrics-token-for-the-test"


@pytest.fixture
def client() -> Client:
    return Client(REMOTE_ADDR=LOCAL)


def test_healthz_answers_without_the_database_and_for_any_host(client):
    # No django_db mark: any query would raise, so the answer needed none.
    answer = client.get("/healthz", HTTP_HOST="10.1.2.3:8000")
    assert answer.status_code == 200
    assert answer.json() == {"status": "ok"}
    assert answer["X-Request-Id"]


@pytest.mark.django_db
def test_readyz_is_200_when_every_part_answers(client):
    answer = client.get("/readyz")
    assert answer.status_code == 200, answer.content
    body = answer.json()
    assert body["status"] == "ready"
    assert body["failed"] == []
    assert set(body["checks"]) == {"database", "redis", "storage", "chain"}
    assert all(check["ok"] for check in body["checks"].values())


@pytest.mark.django_db
def test_readyz_is_503_naming_redis_when_it_does_not_answer(client, settings):
    settings.REDIS_URL = f"redis://127.0.0.1:{free_port()}/0"
    answer = client.get("/readyz")
    assert answer.status_code == 503
    body = answer.json()
    assert body["failed"] == ["redis"]
    assert body["checks"]["redis"]["ok"] is False
    assert "ConnectionError" in body["checks"]["redis"]["detail"]
    assert str(settings.REDIS_URL) not in answer.content.decode()  # no URL in the answer


@pytest.mark.django_db
def test_readyz_is_503_naming_the_chain_when_the_node_does_not_answer(client, settings):
    settings.CHAIN_RPC_URL = f"http://127.0.0.1:{free_port()}"
    answer = client.get("/readyz")
    assert answer.status_code == 503
    assert answer.json()["failed"] == ["chain"]


@pytest.mark.django_db
def test_readyz_is_503_naming_the_storage_when_its_folder_cannot_be(client, settings, tmp_path):
    in_the_way = tmp_path / "a-file"
    in_the_way.write_text("")
    settings.STORAGES = {
        **settings.STORAGES,
        "envelopes": {
            "BACKEND": "sharing.storage.DurableFileSystemStorage",
            "OPTIONS": {"location": str(in_the_way / "envelopes")},
        },
    }
    answer = client.get("/readyz")
    assert answer.status_code == 503
    assert answer.json()["failed"] == ["storage"]


@pytest.mark.django_db
def test_probes_are_neither_rate_limited_nor_logged(client, settings):
    settings.REST_FRAMEWORK = {
        **settings.REST_FRAMEWORK,
        "DEFAULT_THROTTLE_RATES": {
            **settings.REST_FRAMEWORK["DEFAULT_THROTTLE_RATES"],
            "anon": "2/minute",
        },
    }
    with logged_by("portal.access") as access, logged_by("django.request") as errors:
        answers = [client.get("/healthz").status_code for _ in range(20)]
        answers += [client.get("/metrics").status_code for _ in range(5)]
        settings.CHAIN_RPC_URL = f"http://127.0.0.1:{free_port()}"
        answers += [client.get("/readyz").status_code for _ in range(3)]
        api = [client.get("/api/v1/sm2-public-key/").status_code for _ in range(3)]
    assert answers == [200] * 25 + [503] * 3
    assert api[-1] == 429  # the API's anonymous limit is in force meanwhile
    # Only the API requests have access lines.
    assert [r.getMessage().split(" ")[:3] for r in access] == [
        ["GET", "/api/v1/sm2-public-key/", str(code)] for code in api
    ]
    assert not [r for r in errors if "/readyz" in r.getMessage()]


@pytest.mark.django_db
def test_metrics_are_free_from_this_host_and_need_the_token_from_elsewhere(settings):
    settings.METRICS_TOKEN = TOKEN
    local, remote = Client(REMOTE_ADDR=LOCAL), Client(REMOTE_ADDR=ELSEWHERE)
    assert local.get("/metrics").status_code == 200
    refused = remote.get("/metrics")
    assert refused.status_code == 401
    assert refused.json()["error"] == "metrics_token_required"
    assert b"authros_" not in refused.content
    assert remote.get("/metrics", HTTP_AUTHORIZATION="Bearer wrong").status_code == 401
    assert remote.get("/metrics", HTTP_AUTHORIZATION=f"Token {TOKEN}").status_code == 401
    allowed = remote.get("/metrics", HTTP_AUTHORIZATION=f"Bearer {TOKEN}")
    assert allowed.status_code == 200
    assert allowed["Content-Type"].startswith("text/plain")
    assert b"authros_uploads_total" in allowed.content


@pytest.mark.django_db
def test_without_a_token_set_metrics_are_refused_to_everyone_elsewhere(settings):
    settings.METRICS_TOKEN = ""
    remote = Client(REMOTE_ADDR=ELSEWHERE)
    assert remote.get("/metrics").status_code == 401
    assert remote.get("/metrics", HTTP_AUTHORIZATION="Bearer ").status_code == 401


@pytest.mark.django_db
def test_a_forwarded_request_is_not_local_unless_the_proxy_says_so(settings):
    """X-Forwarded-For is believed only as far as API_NUM_PROXIES says (the API throttles'
    rule): a client cannot claim 127.0.0.1, and a proxy on this host that forwards everyone
    from 127.0.0.1 does not make everyone local."""
    settings.METRICS_TOKEN = TOKEN
    local = Client(REMOTE_ADDR=LOCAL)
    remote = Client(REMOTE_ADDR=ELSEWHERE)
    settings.REST_FRAMEWORK = {**settings.REST_FRAMEWORK, "NUM_PROXIES": 0}
    assert remote.get("/metrics", HTTP_X_FORWARDED_FOR=LOCAL).status_code == 401
    assert local.get("/metrics", HTTP_X_FORWARDED_FOR=ELSEWHERE).status_code == 401
    settings.REST_FRAMEWORK = {**settings.REST_FRAMEWORK, "NUM_PROXIES": 1}
    assert local.get("/metrics", HTTP_X_FORWARDED_FOR=ELSEWHERE).status_code == 401
    spoofed = f"{LOCAL}, {ELSEWHERE}"  # the client wrote 127.0.0.1, our proxy appended its peer
    assert local.get("/metrics", HTTP_X_FORWARDED_FOR=spoofed).status_code == 401
    assert local.get("/metrics", HTTP_X_FORWARDED_FOR=LOCAL).status_code == 200


@pytest.mark.django_db
def test_the_scrape_reports_a_source_that_does_not_answer_and_the_others(settings):
    settings.CHAIN_RPC_URL = f"http://127.0.0.1:{free_port()}"
    state_collector.forget()
    text = Client(REMOTE_ADDR=LOCAL).get("/metrics").content.decode()
    state_collector.forget()
    assert 'authros_metrics_source_up{source="chain"} 0.0' in text
    assert 'authros_metrics_source_up{source="database"} 1.0' in text
    assert 'authros_metrics_source_up{source="redis"} 1.0' in text
    assert "authros_chain_head_block" not in text
    assert 'authros_chain_backlog{kind="records"}' in text
    assert 'authros_celery_queue_length{queue="' in text


@pytest.mark.django_db
@pytest.mark.timeout(60)  # a scrape that hangs fails here
def test_a_node_that_never_answers_costs_the_scrape_its_timeout_not_a_hang(settings):
    """A node behind a dead link takes the connection and says nothing (here: a socket that
    listens and never reads): the chain's gauges are left out after the client's timeout,
    `source="chain"` says why, and the rest is served."""
    with socket.create_server(("127.0.0.1", 0)) as silent:
        settings.CHAIN_RPC_URL = f"http://127.0.0.1:{silent.getsockname()[1]}"
        state_collector.forget()
        text = Client(REMOTE_ADDR=LOCAL).get("/metrics").content.decode()
        state_collector.forget()
    assert 'authros_metrics_source_up{source="chain"} 0.0' in text
    assert "authros_operator_balance_wei" not in text
    assert "authros_operator_nonce" not in text
    assert 'authros_metrics_source_up{source="database"} 1.0' in text
    assert "authros_operator_alerts_open 0.0" in text
    assert 'authros_metrics_source_up{source="disk"} 1.0' in text
    assert "authros_disk_free_bytes{" in text


@pytest.mark.parametrize("path", ["/healthz", "/readyz", "/metrics"])
def test_each_probe_answers_options_with_allow_as_haproxys_httpchk_asks(client, path):
    answer = client.options(path)
    assert answer.status_code == 204
    assert answer["Allow"] == "GET, HEAD, OPTIONS"
    assert answer.content == b""


@pytest.mark.django_db
@pytest.mark.parametrize("path", ["/healthz", "/readyz"])
def test_head_gets_the_gets_status_and_length_without_the_body(client, path):
    got = client.get(path)
    head = client.head(path)
    assert (head.status_code, got.status_code) == (200, 200)
    assert head["Content-Length"] == str(len(got.content))
    assert head["Content-Type"] == got["Content-Type"]
    assert head.content == b""


def test_head_of_metrics_needs_what_get_needs(settings):
    settings.METRICS_TOKEN = TOKEN
    assert Client(REMOTE_ADDR=ELSEWHERE).head("/metrics").status_code == 401
    allowed = Client(REMOTE_ADDR=ELSEWHERE).head("/metrics", HTTP_AUTHORIZATION=f"Bearer {TOKEN}")
    assert allowed.status_code == 200


@pytest.mark.parametrize("method", ["post", "put", "delete", "patch"])
def test_other_methods_are_405_with_allow(client, method):
    answer = getattr(client, method)("/healthz")
    assert answer.status_code == 405
    assert answer["Allow"] == "GET, HEAD, OPTIONS"
