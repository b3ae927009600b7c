"""Fixtures of the alerts tests: a real SMTP server (aiosmtpd), a real webhook receiver (an
HTTP server in a thread of the test), and an owner's choices set through the service."""

import json
import socket
import threading
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from email import message_from_bytes
from email.message import Message
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

import pytest
from aiosmtpd.controller import Controller
from django.utils import timezone

from accounts.models import Owner
from alerts.models import AlertKind, AlertPreferences
from alerts.services import alert_preferences_update
from tests.pages.conftest import upload  # noqa: F401  (the fixture, for tests/alerts/)

EVERY_KIND = [kind for kind in AlertKind.values if kind != AlertKind.TEST]


@pytest.fixture(autouse=True)
def _alert_retries_inline(eager_retries) -> None:
    """Deliveries retry: every alerts test runs them inline (tests/conftest.py)."""


class _Inbox:
    """aiosmtpd's handler: every message the server accepted."""

    def __init__(self) -> None:
        self.messages: list[Message] = []
        self.envelopes: list[tuple[str, list[str]]] = []

    async def handle_DATA(self, server, session, envelope) -> str:
        self.envelopes.append((envelope.mail_from, list(envelope.rcpt_tos)))
        self.messages.append(message_from_bytes(envelope.original_content))
        return "250 Message accepted for delivery"


@pytest.fixture
def smtp_server(settings) -> Iterator[_Inbox]:
    """A real SMTP server on a free local port, and Django's SMTP backend pointed at it."""
    inbox = _Inbox()
    # aiosmtpd's start() connects to the port it was given to check the server: not 0.
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    controller = Controller(inbox, hostname="127.0.0.1", port=port)
    controller.start()
    try:
        settings.EMAIL_BACKEND = "django.core.mail.backends.smtp.EmailBackend"
        settings.EMAIL_HOST = "127.0.0.1"
        settings.EMAIL_PORT = port
        settings.EMAIL_USE_TLS = settings.EMAIL_USE_SSL = False
        settings.EMAIL_HOST_USER = settings.EMAIL_HOST_PASSWORD = ""
        yield inbox
    finally:
        controller.stop()


@dataclass
class Received:
    path: str
    headers: dict[str, str]
    body: bytes

    @property
    def payload(self) -> dict:
        return json.loads(self.body)


@dataclass
class Receiver:
    """A webhook receiver: answers each POST with the next of `answers` (then 200)."""

    url: str
    answers: list[tuple[int, dict[str, str]]] = field(default_factory=list)
    received: list[Received] = field(default_factory=list)


@pytest.fixture
def webhook_receiver(settings) -> Iterator[Receiver]:
    settings.ALERTS_WEBHOOK_ALLOW_PRIVATE = True  # it listens on the loopback
    receiver = Receiver(url="")

    class Handler(BaseHTTPRequestHandler):
        def do_POST(self) -> None:
            body = self.rfile.read(int(self.headers["Content-Length"]))
            receiver.received.append(Received(self.path, dict(self.headers.items()), body))
            status, headers = receiver.answers.pop(0) if receiver.answers else (200, {})
            self.send_response(status)
            for name, value in headers.items():
                self.send_header(name, value)
            self.send_header("Content-Length", "2")
            self.end_headers()
            self.wfile.write(b"ok")

        def log_message(self, *args: object) -> None:
            pass

    server = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
    settings.ALERTS_WEBHOOK_PORTS = [server.server_address[1]]
    receiver.url = f"http://127.0.0.1:{server.server_address[1]}/hooks/authros?x=1"
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        yield receiver
    finally:
        server.shutdown()
        server.server_close()
        thread.join()


@pytest.fixture
def alerts_on() -> Callable[..., None]:
    """Choose, for `owner`, which kinds go by e-mail and which to the webhooks."""

    def choose(
        owner: Owner,
        *,
        email: list[str] | None = None,
        webhook: list[str] | None = None,
        address: str = "owner@example.org",
        robot_silent_minutes: int | None = 10,
        gas_low_below_wei: int | None = 1,
    ) -> None:
        alert_preferences_update(
            owner=owner,
            email=address,
            email_kinds=EVERY_KIND if email is None else email,
            webhook_kinds=[] if webhook is None else webhook,
            robot_silent_minutes=robot_silent_minutes,
            gas_low_below_wei=gas_low_below_wei,
        )
        # As if the owner had opened the link sent to the address (tests/pages tests that).
        AlertPreferences.objects.filter(owner=owner).update(email_verified_at=timezone.now())

    return choose
