"""Task events are on by default, so that Flower and `celery events` see every task (the
workers' task-received/started/succeeded and the clients' task-sent); CELERY_TASK_EVENTS=false
turns both off."""

import pytest

from portal.celery import app
from tests.support.fresh_python import fresh_python

EVENTS = (
    "import django; django.setup(); from portal.celery import app; "
    "print(app.conf.worker_send_task_events, app.conf.task_send_sent_event)"
)


def test_workers_and_clients_send_task_events():
    assert app.conf.worker_send_task_events is True
    assert app.conf.task_send_sent_event is True


@pytest.mark.process
def test_an_operator_may_turn_them_off(monkeypatch):
    monkeypatch.setenv("CELERY_TASK_EVENTS", "false")
    assert fresh_python(EVENTS) == "False False"
