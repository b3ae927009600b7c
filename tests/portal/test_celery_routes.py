"""Views' integrity checks have a queue of their own, so they never wait behind chain work."""

from django.conf import settings

from portal.celery import VERIFY_TASKS, app


def _queue(task_name: str) -> str:
    return app.amqp.router.route({}, task_name)["queue"].name


def test_integrity_checks_go_to_the_verify_queue_and_chain_work_to_the_default_one():
    default = app.conf.task_default_queue
    assert _queue("sharing.tasks.records_verify") == f"{default}-verify"
    for chain_work in (
        "sharing.tasks.records_anchor",
        "accounts.tasks.owner_register",
        "sharing.tasks.chain_work_sweep",
    ):
        assert _queue(chain_work) == default


def test_the_route_follows_the_default_queue_chosen_at_run_time():
    before = app.conf.task_default_queue
    app.conf.task_default_queue = "elsewhere"
    try:
        assert _queue("sharing.tasks.records_verify") == "elsewhere-verify"
        assert _queue("sharing.tasks.records_anchor") == "elsewhere"
    finally:
        app.conf.task_default_queue = before


def test_a_worker_started_without_queues_consumes_both():
    names = [queue.name for queue in settings.CELERY_TASK_QUEUES]
    assert names == [
        settings.CELERY_TASK_DEFAULT_QUEUE,
        f"{settings.CELERY_TASK_DEFAULT_QUEUE}-verify",
    ]


def test_the_routed_names_are_the_tasks_names():
    from sharing.tasks import records_verify, series_verify

    assert {records_verify.name, series_verify.name} == VERIFY_TASKS
