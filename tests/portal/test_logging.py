"""Log lines (core/logging.py): one JSON object each, with the request's id and who it acted
for, never a token, a key or content; the id answered in X-Request-Id and carried into the
tasks the request queues."""

import io
import json
import logging
import uuid
from collections.abc import Iterator
from contextlib import contextmanager

import pytest
from django.test import Client
from kombu import Connection

from core.logging import (
    ConsoleFormatter,
    ContextFilter,
    JsonFormatter,
    log_context_reset,
    log_context_set,
    logging_config,
)
from portal.celery import REQUEST_ID_HEADER, app
from sharing.models import Record
from tests.api.conftest import RECORDS, b64, token_client

# Every logger of the portal and its frameworks. (Not the root: a task run inline sets Django's
# logging up again, which replaces the root's handlers, and leaves these loggers' alone.)
LOGGERS = ("portal", "accounts", "sharing", "alerts", "chainworker", "core", "django", "celery")


@contextmanager
def json_lines() -> Iterator[io.StringIO]:
    """What the loggers write meanwhile, as the settings' JSON handler writes it."""
    output = io.StringIO()
    handler = logging.StreamHandler(output)
    handler.setFormatter(JsonFormatter())
    handler.addFilter(ContextFilter())
    for name in LOGGERS:
        logging.getLogger(name).addHandler(handler)
    try:
        yield output
    finally:
        for name in LOGGERS:
            logging.getLogger(name).removeHandler(handler)


def parsed(output: io.StringIO) -> list[dict]:
    return [json.loads(line) for line in output.getvalue().splitlines()]


@pytest.mark.django_db
def test_lines_are_json_with_the_request_id_and_never_a_token_a_key_or_content(
    make_robot, make_owner_token, django_capture_on_commit_callbacks
):
    setup = make_robot()
    _, owner_key = make_owner_token(setup.owner, scopes=("read",))
    sm4_hex = setup.key.hex()
    secret_text = f"the robot's secret reading {uuid.uuid4().hex[:12]}"
    robot = token_client(setup.token)
    with json_lines() as output:
        with django_capture_on_commit_callbacks(execute=True):
            stored = robot.post(
                RECORDS,
                {"envelope": b64(setup.seal(1, plaintext=secret_text.encode()))},
                format="json",
                HTTP_X_REQUEST_ID="upload-1",
            )
        assert stored.status_code == 201, stored.content
        refused = robot.post(
            RECORDS, {"envelope": "not base64 at all", "sm4_key_hex": sm4_hex}, format="json"
        )
        assert refused.status_code == 400
        missing = robot.get(f"{RECORDS}{sm4_hex}/?sm4_key_hex={sm4_hex}&token={setup.token}")
        assert missing.status_code == 404
        record = Record.objects.get(robot=setup.robot)
        viewed = token_client(owner_key).get(f"{RECORDS}{record.id}/content/")
        assert viewed.status_code == 200
    text = output.getvalue()
    lines = parsed(output)
    assert lines, "nothing was logged"
    for line in lines:
        assert {"time", "level", "logger", "message"} <= set(line), line
    # Never a credential, the key or content (the envelope answered to the viewer included).
    for secret in (setup.token, owner_key, sm4_hex, secret_text, viewed.json()["envelope"]):
        assert secret not in text
    access = [line for line in lines if line["logger"] == "portal.access"]
    assert [line["message"].split(" ")[:3] for line in access] == [
        ["POST", RECORDS, "201"],
        ["POST", RECORDS, "400"],
        ["GET", f"{RECORDS}[redacted]/", "404"],
        ["GET", f"{RECORDS}{record.id}/content/", "200"],
    ]
    answers = [stored, refused, missing, viewed]
    assert [line["request_id"] for line in access] == [a["X-Request-Id"] for a in answers]
    assert access[0]["request_id"] == "upload-1"
    assert access[0]["robot"] == str(setup.robot.pk)
    assert access[0]["owner"] == setup.owner.pk
    assert access[3]["owner"] == setup.owner.pk
    assert "robot" not in access[3]
    # What ran as a task (the anchoring, inline here) names the task on its lines.
    anchoring = [line for line in lines if line.get("task") == "sharing.tasks.records_anchor"]
    assert anchoring
    assert all(line["task_id"] for line in anchoring)


@pytest.mark.django_db
def test_a_sane_request_id_is_kept_and_any_other_replaced():
    client = Client(REMOTE_ADDR="127.0.0.1")
    assert client.get("/healthz", HTTP_X_REQUEST_ID="lb-7f3a.9")["X-Request-Id"] == "lb-7f3a.9"
    for bad in ("", "two words", "x" * 129, "line\nbreak", "<script>"):
        answer = client.get("/healthz", HTTP_X_REQUEST_ID=bad)
        assert answer["X-Request-Id"] != bad
        assert uuid.UUID(answer["X-Request-Id"])
    assert uuid.UUID(client.get("/healthz")["X-Request-Id"])


@pytest.mark.filterwarnings("ignore::celery.exceptions.AlwaysEagerIgnored")
def test_a_task_queued_inside_a_request_carries_its_id(settings):
    """The message itself, read back from Redis: the header a worker's task_prerun reads."""
    queue = f"authros-test-headers-{uuid.uuid4().hex[:12]}"
    context = log_context_set(request_id="req-42")
    try:
        app.send_task("sharing.tasks.records_purge", queue=queue)
    finally:
        log_context_reset(context)
    app.send_task("sharing.tasks.records_purge", queue=queue)  # outside any request
    with Connection(settings.CELERY_BROKER_URL) as connection:
        simple = connection.SimpleQueue(queue)
        try:
            first = simple.get(timeout=10)
            second = simple.get(timeout=10)
            first.ack()
            second.ack()
        finally:
            simple.close()
            connection.default_channel.queue_delete(queue)
    assert first.headers[REQUEST_ID_HEADER] == "req-42"
    assert REQUEST_ID_HEADER not in second.headers


def test_the_format_is_chosen_by_log_format():
    assert (
        logging_config(log_format="json", level="INFO")["formatters"]["json"]["()"] is JsonFormatter
    )
    console = logging_config(log_format="console", level="INFO")
    assert console["handlers"]["default"]["formatter"] == "console"
    assert console["formatters"]["console"]["()"] is ConsoleFormatter
    with pytest.raises(ValueError, match="LOG_FORMAT"):
        logging_config(log_format="xml", level="INFO")


def test_a_console_line_is_readable_and_names_the_request():
    record = logging.LogRecord("portal.access", logging.INFO, __file__, 1, "GET %s", ("/x",), None)
    context = log_context_set(request_id="req-7", owner=3)
    try:
        ContextFilter().filter(record)
    finally:
        log_context_reset(context)
    line = ConsoleFormatter().format(record)
    assert line.endswith(f" INFO portal.access {record.process} request_id=req-7 owner=3 GET /x")


def test_a_tasks_return_value_is_logged_only_when_it_is_a_number():
    line = "Task %(name)s[%(id)s] succeeded in %(runtime)ss: %(return_value)s"
    for value, shown in (("12", "12"), ("{'envelope': 'QVIB...'}", "(not logged)")):
        record = logging.LogRecord("celery.app.trace", logging.INFO, __file__, 1, line, None, None)
        record.args = {"name": "t", "id": "1", "runtime": 0.1, "return_value": value}
        ContextFilter().filter(record)
        assert record.getMessage().endswith(f": {shown}")
