"""/metrics counts what happens: uploads and envelopes by result, views with their verdicts,
anchoring transactions and their gas, with latency histograms; and reads state when scraped
(backlog, queues, the chain's head)."""

import re
import threading
import uuid
from datetime import timedelta
from pathlib import Path

import pytest
from django.db import connection
from django.test import Client
from django.urls import resolve
from django.utils import timezone
from prometheus_client.parser import text_string_to_metric_families

from chainworker.services import chain_client, operator_alert_raise, operator_alert_resolve
from core.files import filesystem_free
from portal.metrics import UPLOAD_ROUTES, VIEW_ROUTES
from portal.scrape import state_collector
from sharing.disk import portal_disks
from sharing.models import Record
from tests.api.conftest import RECORDS, b64, token_client

# The uploads run in threads of their own, which see only committed rows.
pytestmark = pytest.mark.django_db(transaction=True)

UPLOADERS = 2
UPLOADS_EACH = 3


def scrape() -> dict[tuple[str, tuple[tuple[str, str], ...]], float]:
    """Every sample of /metrics, as read from 127.0.0.1: {(name, labels): value}."""
    answer = Client(REMOTE_ADDR="127.0.0.1").get("/metrics")
    assert answer.status_code == 200
    return {
        (sample.name, tuple(sorted(sample.labels.items()))): sample.value
        for family in text_string_to_metric_families(answer.content.decode())
        for sample in family.samples
    }


def value(samples: dict, name: str, **labels: str) -> float:
    return samples.get((name, tuple(sorted(labels.items()))), 0.0)


def moved(before: dict, after: dict, name: str, **labels: str) -> float:
    return value(after, name, **labels) - value(before, name, **labels)


def test_counters_move_while_robots_upload_and_owners_view(
    make_robot, make_owner_token, django_capture_on_commit_callbacks
):
    robots = [make_robot() for _ in range(UPLOADERS)]
    before = scrape()
    scrapes: list[dict] = []
    failures: list[BaseException] = []

    def upload_and_view(setup) -> None:
        try:
            client = token_client(setup.token)
            for seq in range(1, UPLOADS_EACH + 1):
                answer = client.post(RECORDS, {"envelope": b64(setup.seal(seq))}, format="json")
                assert answer.status_code == 201, answer.content
        except BaseException as exc:  # seen by the test thread
            failures.append(exc)
        finally:
            connection.close()  # this thread's own

    # Uploads in threads of their own (as web threads), the scrapes meanwhile in this one.
    threads = [threading.Thread(target=upload_and_view, args=(setup,)) for setup in robots]
    for thread in threads:
        thread.start()
    while any(thread.is_alive() for thread in threads):
        scrapes.append(scrape())
    for thread in threads:
        thread.join()
    assert failures == []
    assert scrapes, "no scrape while the uploads ran"

    # A batch of two, a replayed one (refused, changes nothing), and the anchoring inline.
    setup = robots[0]
    client = token_client(setup.token)
    with django_capture_on_commit_callbacks(execute=True):
        batch = {"envelopes": [b64(setup.seal(seq)) for seq in (10, 11)]}
        assert client.post(RECORDS, batch, format="json").status_code == 201
    replayed = client.post(RECORDS, {"envelope": b64(setup.seal(11))}, format="json")
    assert replayed.status_code == 409
    refusal = replayed.json()["error"]
    record = Record.objects.get(robot=setup.robot, seq=10)
    assert record.status == Record.Status.ANCHORED
    _, key = make_owner_token(setup.owner, scopes=("read",))
    assert token_client(key).get(f"{RECORDS}{record.id}/content/").status_code == 200
    state_collector.forget()
    after = scrape()

    stored = UPLOADERS * UPLOADS_EACH + 1
    assert moved(before, after, "authros_uploads_total", result="stored") == stored
    assert moved(before, after, "authros_envelopes_total", result="stored") == stored + 1
    assert moved(before, after, "authros_uploads_total", result=refusal) == 1
    assert moved(before, after, "authros_envelopes_total", result=refusal) == 1
    assert moved(before, after, "authros_upload_duration_seconds_count", result="stored") == stored
    assert moved(before, after, "authros_upload_duration_seconds_sum", result="stored") > 0
    assert moved(before, after, "authros_views_total", result="verified") == 1
    assert moved(before, after, "authros_view_duration_seconds_count", result="verified") == 1
    assert moved(before, after, "authros_verdicts_total", outcome="verified") == 1
    assert moved(before, after, "authros_records_anchored_total") >= 2
    assert (
        moved(before, after, "authros_chain_transactions_total", function="anchorRoot", result="ok")
        >= 1
    )
    assert moved(before, after, "authros_chain_gas_used_total", function="anchorRoot") > 0
    assert (
        moved(
            before,
            after,
            "authros_celery_tasks_total",
            task="sharing.tasks.records_anchor",
            state="SUCCESS",
        )
        >= 1
    )
    assert value(after, "authros_chain_backlog", kind="records") == 0
    assert value(after, "authros_anchoring_oldest_pending_seconds") == 0
    assert value(after, "authros_chain_head_block") > 0
    assert value(after, "authros_chain_head_age_seconds") >= 0
    assert any(name == "authros_celery_queue_length" for name, _ in after)
    # The scrapes taken meanwhile saw the uploads counted as they went.
    counted = [value(s, "authros_uploads_total", result="stored") for s in scrapes]
    assert counted == sorted(counted)


def test_the_backlog_and_its_oldest_record_are_read_when_scraped(make_robot, settings):
    setup = make_robot()
    client = token_client(setup.token)
    for seq in (1, 2, 3):
        assert (
            client.post(RECORDS, {"envelope": b64(setup.seal(seq))}, format="json").status_code
            == 201
        )
    # Two of them waiting, the oldest for ten minutes (as if the chain had been away).
    waiting = Record.objects.filter(robot=setup.robot, seq__in=(1, 2))
    waiting.update(status=Record.Status.PENDING)
    Record.objects.filter(robot=setup.robot, seq=1).update(
        created_at=timezone.now() - timedelta(minutes=10)
    )
    state_collector.forget()
    samples = scrape()
    state_collector.forget()
    assert value(samples, "authros_chain_backlog", kind="records") == 2
    assert 600 <= value(samples, "authros_anchoring_oldest_pending_seconds") < 3600


def test_the_operators_account_open_alerts_and_free_disk_are_read_when_scraped(
    deployed, operator, settings
):
    """What an operator alerts on before it fails the portal: the operator running out of
    funds (or its nonce standing still), alerts nobody resolved, a disk filling up."""
    operator_alert_raise(kind="operator-low-balance", subject=operator.address)
    operator_alert_raise(kind="disk-low", subject="/somewhere")
    operator_alert_raise(kind="disk-low", subject="/elsewhere")
    operator_alert_resolve(kind="disk-low", subject="/elsewhere")
    state_collector.forget()
    samples = scrape()
    state_collector.forget()

    assert value(samples, "authros_metrics_source_up", source="chain") == 1
    assert value(samples, "authros_operator_balance_wei") == float(
        chain_client().balance(operator.address)
    )
    mined = chain_client().w3.eth.get_transaction_count(operator.address)
    assert mined >= 1  # the deployment, at least
    assert value(samples, "authros_operator_nonce") == mined
    assert value(samples, "authros_operator_alerts_open") == 2
    assert value(samples, "authros_metrics_source_up", source="disk") == 1
    free = {
        labels[0][1]: count
        for (name, labels), count in samples.items()
        if name == "authros_disk_free_bytes"
    }
    assert set(free) == {str(folder) for folder in portal_disks()}
    envelopes = str(Path(settings.STORAGES["envelopes"]["OPTIONS"]["location"]).absolute())
    assert envelopes in free
    # Others write to this disk meanwhile: the same order of size, not the same byte.
    assert abs(free[envelopes] - filesystem_free(envelopes)) < 1024**3 // 16


@pytest.mark.parametrize("route", sorted(route for _, route in UPLOAD_ROUTES | VIEW_ROUTES))
def test_the_counted_routes_are_the_portals(route):
    """Renamed routes would silently stop being counted: each one counted resolves to itself."""
    path = "/" + re.sub(r"<\w+:\w+>", str(uuid.uuid4()), route)
    assert resolve(path).route == route


def test_a_process_starting_while_scraped_does_not_fail_the_scrape(tmp_path):
    """A process that is starting creates its counts file empty and sizes it a moment later:
    a scrape in between answers the others' counts, not a 500 (seen under load)."""
    from prometheus_client.mmap_dict import MmapedDict, mmap_key

    from core.metrics import _HostFiles

    (tmp_path / "web").mkdir()
    counts = MmapedDict(str(tmp_path / "web" / "counter_1.db"))
    counts.write_value(mmap_key("uploads_total", "uploads_total", [], [], ""), 3.0, 0.0)
    counts.close()
    (tmp_path / "web" / "counter_2.db").touch()  # the starting process's, still empty
    samples = [sample for family in _HostFiles(tmp_path).collect() for sample in family.samples]
    assert [(sample.name, sample.value) for sample in samples] == [("uploads_total", 3.0)]


def test_hostile_methods_paths_and_headers_add_no_series(make_robot):
    """Audit finding: `authros_http_requests_total` was labelled with the method as sent, so
    100 anonymous requests with made-up methods made 100 series in every process until
    restart. Whatever a client sends, each label keeps a bounded set of values."""
    anonymous = Client(REMOTE_ADDR="203.0.113.9")
    setup = make_robot()
    robot = token_client(setup.token)

    def hostile(round_: int) -> None:
        for i in range(25):
            anonymous.generic(f"X{round_}M{i}", "/")
            anonymous.generic(f"GET{i}", f"/api/v1/records/{uuid.uuid4()}/content/")
            anonymous.get(f"/no/such/path/{uuid.uuid4()}/", HTTP_X_FORWARDED_FOR=f"10.0.0.{i}")
            anonymous.get("/", HTTP_HOST="127.0.0.1", HTTP_USER_AGENT=f"agent-{uuid.uuid4()}")
        robot.post(RECORDS, {"envelope": f"not base64 {uuid.uuid4()}"}, format="json")
        robot.generic(f"POST-{round_}", RECORDS, "{}", content_type="application/json")

    hostile(0)  # every bounded value is seen once
    before = scrape()
    hostile(1)
    hostile(2)
    after = scrape()
    new = set(after) - set(before)
    assert not {key for key in new if key[0].startswith("authros_http_requests")}, new
    methods = {
        dict(labels)["method"] for name, labels in after if name == "authros_http_requests_total"
    }
    assert methods <= {"GET", "HEAD", "POST", "PUT", "PATCH", "DELETE", "OPTIONS", "TRACE", "other"}
    assert "other" in methods
    # The samples of every metric (not only the request counter) stayed as many.
    assert {key for key in new if not key[0].startswith("authros_http_request")} == set()
