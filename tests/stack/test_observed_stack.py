"""The portal as make run serves it (gunicorn, a Celery worker), observed from outside: /metrics
scraped from the web while robots upload adds up the web's and the worker's processes, and the
worker's JSON log lines carry the id of the request that queued their task."""

import base64
import json
import threading
import uuid

import pytest
import requests
from prometheus_client.parser import text_string_to_metric_families

from sharing.models import Record
from tests.support.harness import wait_for
from tests.support.worker_robots import registered_robots

pytestmark = [pytest.mark.worker, pytest.mark.process, pytest.mark.django_db(transaction=True)]

UPLOADS_EACH = 10


def _scrape(url: str) -> dict[tuple[str, tuple], float]:
    answer = requests.get(f"{url}/metrics", timeout=30)
    assert answer.status_code == 200, answer.text
    return {
        (sample.name, tuple(sorted(sample.labels.items()))): sample.value
        for family in text_string_to_metric_families(answer.text)
        for sample in family.samples
    }


def _value(samples: dict, name: str, **labels: str) -> float:
    return samples.get((name, tuple(sorted(labels.items()))), 0.0)


def _json_lines(text: str) -> list[dict]:
    lines = []
    for line in text.splitlines():
        if line.startswith("{"):
            try:
                lines.append(json.loads(line))
            except ValueError:
                continue
    return lines


def test_metrics_add_up_the_web_and_the_worker_and_logs_carry_request_ids(
    worker_stack, make_owner_token, tmp_path
):
    stack = worker_stack(workers=0)
    metrics = tmp_path / "metrics"
    stack.start_worker("w0", env={**stack.env(), "PROMETHEUS_MULTIPROC_DIR": str(metrics / "w0")})
    setups = registered_robots(2)
    url = stack.start_web(
        workers=2, env={**stack.env(), "PROMETHEUS_MULTIPROC_DIR": str(metrics / "web")}
    )
    before = _scrape(url)
    sent: list[str] = []
    answers: list[int] = []

    def upload(setup) -> None:
        for seq in range(1, UPLOADS_EACH + 1):
            request_id = f"upload-{uuid.uuid4().hex[:12]}"
            answer = requests.post(
                f"{url}/api/v1/records/",
                json={"envelope": base64.b64encode(setup.seal(seq)).decode()},
                headers={"Authorization": f"Token {setup.token}", "X-Request-Id": request_id},
                timeout=60,
            )
            assert answer.headers["X-Request-Id"] == request_id
            sent.append(request_id)
            answers.append(answer.status_code)

    threads = [threading.Thread(target=upload, args=(setup,)) for setup in setups]
    for thread in threads:
        thread.start()
    scrapes = []
    while any(thread.is_alive() for thread in threads):
        scrapes.append(_scrape(url))  # while the uploads run
    for thread in threads:
        thread.join()
    stored = len(setups) * UPLOADS_EACH
    assert answers == [201] * stored
    wait_for(
        lambda: Record.objects.filter(status=Record.Status.ANCHORED).count() == stored,
        timeout=120,
        what="every record anchored",
    )
    record = Record.objects.filter(robot=setups[0].robot).first()
    _, key = make_owner_token(setups[0].owner, scopes=("read",))
    view_id = f"view-{uuid.uuid4().hex[:12]}"
    viewed = requests.get(
        f"{url}/api/v1/records/{record.id}/content/",
        headers={"Authorization": f"Token {key}", "X-Request-Id": view_id},
        timeout=60,
    )
    assert viewed.status_code == 200, viewed.text
    after = _scrape(url)

    assert scrapes
    assert (
        _value(after, "authros_uploads_total", result="stored")
        - _value(before, "authros_uploads_total", result="stored")
        == stored
    )
    assert _value(after, "authros_views_total", result="verified") == 1
    # Counted by the worker's processes, read through the web's /metrics.
    assert _value(after, "authros_records_anchored_total") == stored
    assert _value(after, "authros_verdicts_total", outcome="verified") == 1
    assert (
        _value(after, "authros_chain_transactions_total", function="anchorRoot", result="ok") >= 1
    )
    assert _value(after, "authros_chain_gas_used_total", function="anchorRoot") > 0
    assert ("authros_chain_backlog", (("kind", "records"),)) in after  # read at scrape time
    assert _value(after, "authros_chain_head_block") > 0

    worker = _json_lines((stack.logs / "w0.log").read_text())
    anchoring = [line for line in worker if line.get("task") == "sharing.tasks.records_anchor"]
    assert anchoring, "the worker logged no anchoring line"
    assert {line.get("request_id") for line in anchoring} & set(sent)
    verify = [line for line in worker if line.get("task") == "sharing.tasks.records_verify"]
    assert verify
    assert {line.get("request_id") for line in verify} == {view_id}
    web = _json_lines((stack.logs / "web.log").read_text())
    access = [line for line in web if line.get("logger") == "portal.access"]
    assert {line["request_id"] for line in access} >= {*sent, view_id}
    assert not [line for line in access if "/metrics" in line["message"]]
