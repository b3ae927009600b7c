"""Where the portal's Redis is, from one URL (REDIS_URL, CELERY_BROKER_URL), in one of three forms:

- a plain Redis, as redis-py reads it: `redis://[[user]:password@]host:6379/DB`, `rediss://...`
  (TLS) or `unix:///path/redis.sock?db=DB`;
- Redis behind Sentinels, which name the master and follow a failover:
  `sentinel://[[user]:password@]host1:26379,host2:26379,host3:26379/DB?master=NAME`
  (the password is the master's; `sentinel_password=...` if the Sentinels ask for one too);
- a Redis Cluster (startup nodes; the slots are asked of them):
  `redis+cluster://[[user]:password@]host1:6379,host2:6379` (`rediss+cluster://` with TLS). A
  Cluster has no databases but 0, and cannot carry Celery's broker or results: kombu has no
  Cluster transport, so the broker is then a plain or Sentinel Redis of its own.

Celery is given the same Redis in its own words (celery_redis): kombu's and Celery's Sentinel
transport read `sentinel://host1:26379/DB;sentinel://host2:26379/DB` with the master's name in
the `master_name` transport option. Read by the settings, so nothing here imports Django.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal
from urllib.parse import parse_qsl, unquote

import redis
from redis.backoff import ExponentialWithJitterBackoff
from redis.cluster import ClusterNode, NodesManager, RedisCluster
from redis.exceptions import RedisClusterException
from redis.retry import Retry
from redis.sentinel import Sentinel

SENTINEL = "sentinel"
CLUSTER_SCHEMES = {"redis+cluster": False, "rediss+cluster": True}  # scheme: TLS
PLAIN_SCHEMES = ("redis", "rediss", "unix")
SENTINEL_PORT = 26379
REDIS_PORT = 6379
SOCKET_TIMEOUT = 5.0
# A command that fails on a broken connection is tried again this often, after 10, 20 and 40 ms
# (with jitter, at most 100 ms): enough for a connection the server closed or a Sentinel's
# new master, while a Redis that is down costs a request a tenth of a second per command.
# redis-py's default (10 retries up to 1 s apart) made every command wait about 3 s.
RETRIES = 3
RETRY_BACKOFF = ExponentialWithJitterBackoff(base=0.01, cap=0.1)


class RedisUrlError(ValueError):
    """The Redis URL cannot be used; the message says why and what to write."""


@dataclass(frozen=True)
class RedisTarget:
    """One Redis URL, read: what kind of Redis, and the nodes to ask first."""

    kind: Literal["plain", "sentinel", "cluster"]
    url: str
    nodes: tuple[tuple[str, int], ...] = ()  # the Sentinels, or the Cluster's startup nodes
    userinfo: str = ""  # as written in the URL, percent-encoded, without the "@"
    db: int = 0
    master: str = ""
    sentinel_password: str = field(default="", repr=False)
    ssl: bool = False

    @property
    def username(self) -> str | None:
        name = self.userinfo.partition(":")[0]
        return unquote(name) if name else None

    @property
    def password(self) -> str | None:
        _, colon, secret = self.userinfo.partition(":")
        return unquote(secret) if colon and secret else None


@dataclass(frozen=True)
class CeleryRedis:
    """A broker or result backend URL as Celery reads it, and its transport options."""

    url: str
    transport_options: dict[str, object]


def redis_target(url: str) -> RedisTarget:
    """Read a Redis URL in any of the three forms; RedisUrlError if it is none of them."""
    scheme = url.partition("://")[0].lower() if "://" in url else ""
    if scheme in PLAIN_SCHEMES:
        return RedisTarget("plain", url)
    if scheme == SENTINEL:
        return _sentinel_target(url)
    if scheme in CLUSTER_SCHEMES:
        return _cluster_target(url, ssl=CLUSTER_SCHEMES[scheme])
    raise RedisUrlError(
        f"{_safe(url)!r} is no Redis URL: redis://, rediss://, unix://, "
        "sentinel://HOST:PORT,HOST:PORT/DB?master=NAME or redis+cluster://HOST:PORT,HOST:PORT"
    )


def redis_client_for(
    url: str,
    *,
    socket_timeout: float = SOCKET_TIMEOUT,
    socket_connect_timeout: float = SOCKET_TIMEOUT,
) -> redis.Redis | RedisCluster:
    """A client for the Redis at url: for Sentinels one that asks them for the master on every
    new connection (so it follows a failover), for a Cluster redis-py's cluster client."""
    target = redis_target(url)
    timeouts = {"socket_timeout": socket_timeout, "socket_connect_timeout": socket_connect_timeout}
    if target.kind == "plain":
        return redis.Redis.from_url(url, retry=_retry(), **timeouts)
    credentials = {"username": target.username, "password": target.password}
    if target.kind == "sentinel":
        sentinel_auth = {"password": target.sentinel_password} if target.sentinel_password else {}
        sentinel = Sentinel(
            list(target.nodes),
            sentinel_kwargs={**timeouts, **sentinel_auth, "retry": _retry()},
            db=target.db,
            retry=_retry(),
            **credentials,
            **timeouts,
        )
        return sentinel.master_for(target.master)
    try:
        client = RedisCluster(
            startup_nodes=[ClusterNode(host, port) for host, port in target.nodes],
            ssl=target.ssl,
            retry=_retry(),
            **credentials,
            **timeouts,
        )
    except RedisClusterException as exc:
        raise redis.ConnectionError(str(exc)) from exc
    client.nodes_manager.__class__ = _ClusterNodes
    return client


def _retry() -> Retry:
    """The retry policy of the portal's clients (RETRIES), one object per client."""
    return Retry(RETRY_BACKOFF, RETRIES)


def celery_redis(url: str, *, setting: str) -> CeleryRedis:
    """What Celery is given for the broker or result backend at url (named `setting` in
    errors): a Sentinel URL in kombu's form, any other URL as it is. A Cluster is refused."""
    scheme = url.partition("://")[0].lower()
    if scheme not in (SENTINEL, *CLUSTER_SCHEMES):
        return CeleryRedis(url, {})
    target = redis_target(url)
    if target.kind == "cluster":
        raise RedisUrlError(
            f"{setting} is a Redis Cluster ({_safe(url)}), which Celery cannot use (kombu has no "
            f"Cluster transport): set {setting} to a plain redis:// or a sentinel:// Redis of "
            "its own (see docs/operations.md)"
        )
    auth = f"{target.userinfo}@" if target.userinfo else ""
    kombu_url = ";".join(
        f"sentinel://{auth}{_host(host)}:{port}/{target.db}" for host, port in target.nodes
    )
    options: dict[str, object] = {"master_name": target.master}
    if target.sentinel_password:
        options["sentinel_kwargs"] = {"password": target.sentinel_password}
    return CeleryRedis(kombu_url, options)


class _ClusterNodes(NodesManager):
    """A Cluster none of whose nodes answers (or whose slots are not all served) is a
    redis.ConnectionError, as an outage of one Redis is: the portal's code catches RedisError,
    and redis-py raises its RedisClusterException, which is none."""

    def initialize(self, *args: object, **kwargs: object) -> None:
        try:
            super().initialize(*args, **kwargs)
        except RedisClusterException as exc:
            raise redis.ConnectionError(str(exc)) from exc


# --- reading the URL ---------------------------------------------------------------------------


def _sentinel_target(url: str) -> RedisTarget:
    if ";" in url:
        raise RedisUrlError(
            "write the Sentinels in one sentinel:// URL, separated by commas: "
            "sentinel://HOST:PORT,HOST:PORT/DB?master=NAME (not kombu's ';' list)"
        )
    userinfo, nodes, path, query = _split(url, default_port=SENTINEL_PORT)
    options = _query(url, query, allowed={"master", "sentinel_password"})
    if not options.get("master"):
        raise RedisUrlError(
            f"{_safe(url)!r} names no master: add ?master=NAME (the name the Sentinels monitor)"
        )
    return RedisTarget(
        "sentinel",
        url,
        nodes,
        userinfo,
        db=_db(url, path),
        master=options["master"],
        sentinel_password=options.get("sentinel_password", ""),
    )


def _cluster_target(url: str, *, ssl: bool) -> RedisTarget:
    userinfo, nodes, path, query = _split(url, default_port=REDIS_PORT)
    _query(url, query, allowed=set())
    if _db(url, path) != 0:
        raise RedisUrlError(f"{_safe(url)!r}: a Redis Cluster has only database 0")
    return RedisTarget("cluster", url, nodes, userinfo, ssl=ssl)


def _split(url: str, *, default_port: int) -> tuple[str, tuple[tuple[str, int], ...], str, str]:
    """userinfo, [(host, port)], path, query of `scheme://userinfo@h:p,h:p/path?query`."""
    # By hand: urlsplit refuses a list of hosts with an [IPv6] among them.
    rest, _, query = url.partition("://")[2].partition("?")
    netloc, slash, path = rest.partition("/")
    userinfo, _, hosts = netloc.rpartition("@")
    nodes = tuple(_node(url, item, default_port) for item in hosts.split(",") if item)
    if not nodes:
        raise RedisUrlError(f"{_safe(url)!r} names no host")
    return userinfo, nodes, slash + path, query


def _node(url: str, item: str, default_port: int) -> tuple[str, int]:
    if item.startswith("["):  # [IPv6]:port
        host, _, rest = item[1:].partition("]")
        port = rest.removeprefix(":")
    else:
        host, _, port = item.partition(":")
    if not host or (port and not port.isdigit()):
        raise RedisUrlError(f"{_safe(url)!r}: {item!r} is no HOST:PORT")
    return host, int(port) if port else default_port


def _db(url: str, path: str) -> int:
    number = path.strip("/") or "0"
    if not number.isdigit():
        raise RedisUrlError(f"{_safe(url)!r}: the path must be a database number, not {path!r}")
    return int(number)


def _query(url: str, query: str, *, allowed: set[str]) -> dict[str, str]:
    options = dict(parse_qsl(query, keep_blank_values=True))
    if unknown := sorted(set(options) - allowed):
        raise RedisUrlError(
            f"{_safe(url)!r}: unknown option(s) {', '.join(unknown)} "
            f"(known: {', '.join(sorted(allowed)) or 'none'})"
        )
    return options


def _host(host: str) -> str:
    return f"[{host}]" if ":" in host else host


def _safe(url: str) -> str:
    """The URL without its passwords (in the userinfo or the query), for messages."""
    scheme, sep, rest = url.partition("://")
    rest = rest.partition("?")[0]
    userinfo, at, hosts = rest.rpartition("@")
    if not at:
        return f"{scheme}{sep}{rest}"
    return f"{scheme}{sep}{userinfo.partition(':')[0]}:***@{hosts}"
