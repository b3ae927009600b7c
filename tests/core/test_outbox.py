"""Queueing by name: fire-and-forget tasks keep no result, and nobody listens for one."""

import pytest
from celery import current_app

from core.outbox import dispatch, enqueue


@pytest.fixture
def sent(monkeypatch) -> list[dict]:
    """What would go to the broker: send_task's options, queue not touched."""
    calls: list[dict] = []
    current_app.conf.task_always_eager = False  # every test sets it again (tests/conftest.py)
    monkeypatch.setattr(
        current_app, "send_task", lambda name, **options: calls.append(options | {"name": name})
    )
    return calls


def test_a_queued_task_keeps_no_result(sent):
    assert enqueue("sharing.tasks.records_anchor", 7, countdown=2.0) is True
    (options,) = sent
    assert options["name"] == "sharing.tasks.records_anchor"
    assert options["args"] == (7,)
    assert options["countdown"] == 2.0
    # The Redis result backend otherwise subscribes to the task's result in this process.
    assert options["ignore_result"] is True


def test_a_dispatched_task_keeps_its_result_for_who_waits(sent):
    dispatch("sharing.tasks.records_verify", ["id"], 1)
    assert sent[0]["ignore_result"] is False
