"""The three forms of a Redis URL (core/redis_url.py), and what Celery is given for each."""

import pytest

from core.redis_url import RedisUrlError, celery_redis, redis_target

pytestmark = pytest.mark.nodb


def test_a_sentinel_url_names_the_sentinels_the_master_and_the_database():
    target = redis_target(
        "sentinel://:s%40cret@10.0.0.1:26379,10.0.0.2,[fd00::3]:26380/4?master=authros"
    )
    assert target.kind == "sentinel"
    assert target.nodes == (("10.0.0.1", 26379), ("10.0.0.2", 26379), ("fd00::3", 26380))
    assert (target.master, target.db, target.password, target.username) == (
        "authros",
        4,
        "s@cret",
        None,
    )


def test_celery_is_given_the_sentinels_in_kombus_form_with_master_name():
    given = celery_redis(
        "sentinel://user:pw@h1:26379,h2:26380/2?master=authros&sentinel_password=sp",
        setting="CELERY_BROKER_URL",
    )
    assert given.url == "sentinel://user:pw@h1:26379/2;sentinel://user:pw@h2:26380/2"
    assert given.transport_options == {
        "master_name": "authros",
        "sentinel_kwargs": {"password": "sp"},
    }
    plain = "redis://127.0.0.1:6379/0"
    assert celery_redis(plain, setting="CELERY_BROKER_URL").url == plain
    assert celery_redis(plain, setting="CELERY_BROKER_URL").transport_options == {}


def test_a_cluster_url_names_its_startup_nodes_and_is_no_broker():
    target = redis_target("rediss+cluster://:pw@n1:7000,n2")
    assert (target.kind, target.nodes, target.ssl, target.password) == (
        "cluster",
        (("n1", 7000), ("n2", 6379)),
        True,
        "pw",
    )
    with pytest.raises(RedisUrlError, match="CELERY_RESULT_BACKEND is a Redis Cluster") as refused:
        celery_redis("redis+cluster://:hunter2@n1:7000", setting="CELERY_RESULT_BACKEND")
    assert "hunter2" not in str(refused.value)


@pytest.mark.parametrize(
    ("url", "reason"),
    [
        ("sentinel://h1:26379/0", "names no master"),
        ("sentinel://h1:26379;sentinel://h2:26379/0?master=m", "separated by commas"),
        ("sentinel://h1:port/0?master=m", "is no HOST:PORT"),
        ("sentinel://h1/zero?master=m", "database number"),
        ("sentinel://h1/0?master=m&mastr=n", "unknown option"),
        ("sentinel:///0?master=m", "names no host"),
        ("redis+cluster://n1:7000/1", "only database 0"),
        ("memcached://h1", "is no Redis URL"),
    ],
)
def test_a_url_that_cannot_be_used_says_why(url, reason):
    with pytest.raises(RedisUrlError, match=reason):
        redis_target(url)


def test_messages_never_show_a_password():
    with pytest.raises(RedisUrlError) as refused:
        redis_target("sentinel://:hunter2@h1/0?sentinel_password=hunter3")
    assert "hunter" not in str(refused.value)


@pytest.mark.parametrize("scheme", ["redis", "sentinel"])
def test_a_redis_that_is_down_costs_a_command_a_tenth_of_a_second_of_waiting(scheme, monkeypatch):
    import redis
    import redis.retry

    from core.redis_url import redis_client_for
    from stack.anvil import free_port

    waits: list[float] = []
    monkeypatch.setattr(redis.retry, "sleep", waits.append)
    port = free_port()
    url = {
        "redis": f"redis://127.0.0.1:{port}/0",
        "sentinel": f"sentinel://127.0.0.1:{port}/0?master=portal",
    }[scheme]
    client = redis_client_for(url, socket_timeout=1, socket_connect_timeout=1)
    with pytest.raises(redis.ConnectionError):
        client.ping()
    # redis-py's default retries ten times up to a second apart: about 3 s a command.
    assert waits, "no retry at all"
    assert sum(waits) <= 0.5, waits
