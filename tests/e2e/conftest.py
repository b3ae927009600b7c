"""Fixtures of the browser tests: Debian's Chromium driven by Playwright, the worker stack,
and numbered screenshots of the steps.

The portal runs in pytest-django's live server (a thread of the test process, sharing its
settings and test database; it serves /static/ through django.contrib.staticfiles). Real
Celery workers, beat and anvil come from tests/support/harness.py: the record page runs its
integrity check through the worker.
"""

from collections.abc import Iterator
from pathlib import Path

import pytest
from django.db import connections
from playwright.sync_api import Browser, sync_playwright

from chainworker import services as chain_services
from tests.support.harness import WorkerStack
from tests.support.screenshots import ARTIFACTS

CHROMIUM = "/usr/bin/chromium"
# Nothing may leave the machine: no component updates, sync, QUIC probes or field trials.
CHROMIUM_ARGS = [
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
]


@pytest.fixture
def stack(tmp_path, settings) -> Iterator[WorkerStack]:
    """anvil with the contract deployed, two workers (so a view's integrity check does not
    wait behind anchoring) and beat."""
    stack = WorkerStack(tmp_path)
    try:
        stack.configure_test_process(settings)
        chain_services._clients.clear()
        chain_services.contract_deploy()
        stack.start_worker("w0")
        stack.start_worker("w1")
        stack.start_beat()
        yield stack
    finally:
        stack.stop()


@pytest.fixture
def browser(monkeypatch) -> Iterator[Browser]:
    # Playwright's sync API leaves its event loop marked running in this thread, and Django
    # refuses ORM calls there; the test's own reads and writes are plain synchronous code.
    monkeypatch.setenv("DJANGO_ALLOW_ASYNC_UNSAFE", "true")
    with sync_playwright() as playwright:
        chromium = playwright.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
        try:
            yield chromium
        finally:
            chromium.close()
            # Django keeps the connections opened while Playwright runs apart from the
            # thread's own (asgiref sees Playwright's loop as running): close them here, or
            # they outlive the test and PostgreSQL cannot drop the test database.
            connections.close_all()


@pytest.fixture
def artifacts() -> Path:
    """Where the screenshots go; they are kept after the test (test-artifacts/ is ignored)."""
    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    for old in ARTIFACTS.glob("*.png"):
        old.unlink()
    return ARTIFACTS
