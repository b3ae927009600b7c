"""Webhook transport: which URLs the portal POSTs to, and the signed POST itself.

A URL's host is resolved once; every address it resolves to must be globally routable (not
loopback, private, link-local, shared, reserved, site-local or multicast, nor an IPv6 spelling
that carries an inner IPv4 address: IPv4-compatible, mapped, translated, NAT64, 6to4, Teredo)
unless ALERTS_WEBHOOK_ALLOW_PRIVATE, and the POST then connects to that very address (TLS still
checks the host's name), so a DNS answer that changes between the check and the connection
cannot reach an inner address (urllib3 is handed the IP literal, never the name). Only ports
80 and 443 (or ALERTS_WEBHOOK_PORTS); no user name, password or fragment in the URL. Redirects
are not followed; the timeout is short.
"""

import hashlib
import hmac
import ipaddress
import socket
import ssl
from dataclasses import dataclass
from urllib.parse import urlsplit

import urllib3
from django.conf import settings

from alerts.errors import DeliveryFailed, WebhookUrlRefused

SIGNATURE_VERSION = "v1"
_DEFAULT_PORTS = {"http": 80, "https": 443}
# The start of a receiver's answer kept in the delivery log's error; the rest is not read.
_ANSWER_KEPT = 200


@dataclass(frozen=True)
class ResolvedUrl:
    scheme: str
    host: str
    port: int
    target: str  # path and query
    address: str  # the IP address the POST connects to


def webhook_signature(*, secret: str, timestamp: int, body: bytes) -> str:
    """`v1=` and the hex HMAC-SHA256, under the endpoint's secret (its UTF-8 bytes), of the
    timestamp in decimal, a full stop, and the exact body."""
    mac = hmac.new(secret.encode(), f"{timestamp}.".encode() + body, hashlib.sha256)
    return f"{SIGNATURE_VERSION}={mac.hexdigest()}"


def webhook_url_check(url: str) -> ResolvedUrl:
    """The URL, resolved to the address to connect to; WebhookUrlRefused if the portal must not
    POST there."""
    try:
        parts = urlsplit(url)
        port = parts.port
    except ValueError:
        raise WebhookUrlRefused("that is not a valid URL") from None
    if parts.scheme not in _DEFAULT_PORTS:
        raise WebhookUrlRefused("a webhook URL starts with https:// (or http://)")
    if not parts.hostname:
        raise WebhookUrlRefused("the URL names no host")
    if "@" in parts.netloc:
        raise WebhookUrlRefused("put no user name or password in the URL: the signature proves it")
    if "#" in url:
        raise WebhookUrlRefused("a webhook URL has no #fragment: the receiver never sees it")
    port = _DEFAULT_PORTS[parts.scheme] if port is None else port
    if port not in _DEFAULT_PORTS.values() and port not in settings.ALERTS_WEBHOOK_PORTS:
        raise WebhookUrlRefused(
            f"port {port} is not allowed: webhooks go to ports 80 and 443"
            + (f" (or {_ports_listed()})" if settings.ALERTS_WEBHOOK_PORTS else "")
        )
    try:
        infos = socket.getaddrinfo(parts.hostname, port, type=socket.SOCK_STREAM)
    except (socket.gaierror, UnicodeError):
        raise WebhookUrlRefused(f"the host {parts.hostname} does not resolve") from None
    addresses = list(dict.fromkeys(info[4][0] for info in infos))
    for address in addresses:
        _address_check(address, host=parts.hostname)
    target = parts.path or "/"
    if parts.query:
        target += "?" + parts.query
    return ResolvedUrl(parts.scheme, parts.hostname, port, target, addresses[0])


def _ports_listed() -> str:
    return ", ".join(str(port) for port in sorted(settings.ALERTS_WEBHOOK_PORTS))


# IPv6 spellings of an IPv4 address, and prefixes that are not globally routable though
# Python's is_global (3.11) says they are: refused whatever they embed.
_NEVER_ROUTED = tuple(
    ipaddress.ip_network(net)
    for net in (
        "::/96",  # IPv4-compatible ::a.b.c.d (deprecated, RFC 4291 2.5.5.1)
        "::ffff:0:0:0/96",  # SIIT IPv4-translated ::ffff:0:a.b.c.d (RFC 2765)
        "64:ff9b:1::/48",  # NAT64 local use (RFC 8215)
        "2001::/32",  # Teredo (RFC 4380)
        "2002::/16",  # 6to4 (RFC 3056)
        "fec0::/10",  # site-local (deprecated, RFC 3879)
    )
)
# NAT64's well-known prefix (RFC 6052): on a DNS64 network a public IPv4-only receiver is
# reached this way, so the IPv4 address in its last 32 bits is checked instead.
_NAT64 = ipaddress.ip_network("64:ff9b::/96")


def globally_routable(address: str) -> bool:
    """Whether the portal may connect to `address` (IPv4 or IPv6, zone id ignored)."""
    ip = ipaddress.ip_address(address.split("%", 1)[0])
    if isinstance(ip, ipaddress.IPv6Address):
        if ip.ipv4_mapped is not None:
            ip = ip.ipv4_mapped
        elif ip in _NAT64:
            ip = ipaddress.IPv4Address(int(ip) & 0xFFFFFFFF)
        elif any(ip in net for net in _NEVER_ROUTED):
            return False
    return ip.is_global and not ip.is_multicast


def _address_check(address: str, *, host: str) -> None:
    if settings.ALERTS_WEBHOOK_ALLOW_PRIVATE or globally_routable(address):
        return
    raise WebhookUrlRefused(
        f"the host {host} is not a globally routable address ({address}): webhooks go to "
        "public addresses only"
    )


@dataclass(frozen=True)
class WebhookAnswer:
    status: int
    start: str  # the first characters of the answer's body


def webhook_post(*, url: str, body: bytes, headers: dict[str, str]) -> WebhookAnswer:
    """POST `body` to `url` (checked again now) at the address it resolved to; the answer.
    Raises WebhookUrlRefused for a refused URL, DeliveryFailed when nothing answered."""
    resolved = webhook_url_check(url)
    timeout = urllib3.Timeout(
        connect=settings.ALERTS_WEBHOOK_TIMEOUT, read=settings.ALERTS_WEBHOOK_TIMEOUT
    )
    host_header = resolved.host
    if ":" in host_header:
        host_header = f"[{host_header}]"
    if resolved.port != _DEFAULT_PORTS[resolved.scheme]:
        host_header += f":{resolved.port}"
    pool: urllib3.HTTPConnectionPool
    if resolved.scheme == "https":
        pool = urllib3.HTTPSConnectionPool(
            resolved.address,
            resolved.port,
            timeout=timeout,
            retries=False,
            maxsize=1,
            ssl_context=ssl.create_default_context(),
            server_hostname=resolved.host,
            assert_hostname=resolved.host,
        )
    else:
        pool = urllib3.HTTPConnectionPool(
            resolved.address, resolved.port, timeout=timeout, retries=False, maxsize=1
        )
    try:
        response = pool.urlopen(
            "POST",
            resolved.target,
            body=body,
            headers={**headers, "Host": host_header},
            redirect=False,
            retries=False,
            preload_content=False,
            assert_same_host=False,
        )
        try:
            start = response.read(_ANSWER_KEPT, decode_content=False)
        finally:
            response.release_conn()
    except urllib3.exceptions.HTTPError as exc:
        raise DeliveryFailed(f"no answer from {resolved.host}: {exc.__class__.__name__}") from None
    finally:
        pool.close()
    return WebhookAnswer(response.status, start.decode("utf-8", "replace"))
