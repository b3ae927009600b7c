"""The direct checks' transport (sharing/verification/direct.py) on the real Redis, with a
stand-in for the task's function: no server, no request; a served request answered once, by
one server; the worker's IdentityMismatch raised as it raised it; any other failure of the
check answered as a failure, the server serving on; an answer not read in time a timeout."""

import threading

import pytest
from celery.exceptions import TimeoutError as CeleryTimeoutError

from accounts.errors import IdentityMismatch
from sharing.verification import direct


@pytest.fixture
def serving():
    stops: list[threading.Event] = []

    def serve(run) -> None:
        stops.append(direct.direct_checks_serving(run))
        for _ in range(200):
            if direct.direct_checks_served():
                return
            threading.Event().wait(0.05)
        raise AssertionError("the server never said it serves")

    yield serve
    for stop in stops:
        stop.set()


def test_without_a_server_nothing_is_asked():
    assert not direct.direct_checks_served()
    assert direct.direct_check_send(["a"], 1) is None


def test_a_request_is_answered_by_the_function_once(serving):
    calls = []

    def run(record_ids, viewer_id):
        calls.append((record_ids, viewer_id))
        return [{"record_id": record_ids[0], "viewer": viewer_id}]

    serving(run)
    asked = direct.direct_check_send(["r1"], 7)
    assert asked.get(timeout=10) == [{"record_id": "r1", "viewer": 7}]
    assert calls == [(["r1"], 7)]
    with pytest.raises(CeleryTimeoutError):  # answered once: nothing more to read
        asked.get(timeout=0.2)


def test_refusals_and_failures_come_back_and_the_server_serves_on(serving):
    def run(what):
        if what == "identity":
            raise IdentityMismatch("the commitment on chain differs")
        if what == "broken":
            raise ValueError("no such thing")
        return what

    serving(run)
    with pytest.raises(IdentityMismatch, match="commitment on chain differs"):
        direct.direct_check_send("identity").get(timeout=10)
    with pytest.raises(RuntimeError, match="ValueError: no such thing"):
        direct.direct_check_send("broken").get(timeout=10)
    assert direct.direct_check_send("fine").get(timeout=10) == "fine"


def test_an_answer_read_late_is_still_the_answer(serving):
    release = threading.Event()

    def run(what):
        release.wait(10)
        return what

    serving(run)
    asked = direct.direct_check_send("late")
    with pytest.raises(CeleryTimeoutError):
        asked.get(timeout=0.3)
    release.set()
    assert asked.get(timeout=10) == "late"  # read after all, then dropped
    asked.forget()
