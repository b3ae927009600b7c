"""Schemathesis against a live portal: no 500, and every answer as the schema says.

The schema is loaded from the running server's `/api/schema/`; every operation is fuzzed
with valid and invalid inputs, as a robot (token), as an owner's script (owner API tokens: one
with both scopes, one that only reads) and as an owner's browser (session and CSRF token).
Real record ids, owners and envelopes are mixed in, so that the fuzz reaches the answers
behind validation too: content, grants, uploads that are stored.
"""

import base64
import itertools
from collections.abc import Callable
from dataclasses import dataclass
from datetime import timedelta
from typing import Any

import pytest
import schemathesis
from django.test import Client
from django.utils.crypto import get_random_string
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.errors import Unsatisfiable
from schemathesis import GenerationMode
from schemathesis.errors import FailureGroup

from accounts.services.api_tokens import owner_token_create
from sharing.services.grants import grant_create
from tests.support.robot_setup import RobotSetup

pytestmark = [pytest.mark.slow, pytest.mark.django_db(transaction=True)]

EXAMPLES_PER_OPERATION = 40
# The operations are fuzzed in this many tests, each its own share of them (round robin by
# operation id), so that the suite's workers share the run: one test of every operation was
# the suite's long pole (248 s on PostgreSQL).
SHARDS = 4
# Exports (issue 16): a valid one runs a whole export inline, so fewer examples.
EXAMPLES_OF = {"exports_create": 5, "exports_list": 3, "exports_detail": 3, "exports_file": 3}


@dataclass
class Identity:
    name: str
    headers: dict[str, str]
    cookies: dict[str, str]


def _identities(setup: RobotSetup) -> list[Identity]:
    browser = Client()
    browser.force_login(setup.owner.user)
    csrf = get_random_string(32)
    _, owner_key = owner_token_create(
        owner=setup.owner, name="fuzz", scopes=["read", "share"], expires_in=timedelta(days=1)
    )
    _, reader_key = owner_token_create(
        owner=setup.owner, name="fuzz-read", scopes=["read"], expires_in=timedelta(days=1)
    )
    return [
        Identity("robot token", {"Authorization": f"Token {setup.token}"}, {}),
        Identity("owner token", {"Authorization": f"Token {owner_key}"}, {}),
        Identity("read-only owner token", {"Authorization": f"Token {reader_key}"}, {}),
        Identity(
            "browser session",
            {"X-CSRFToken": csrf},
            {"sessionid": browser.cookies["sessionid"].value, "csrftoken": csrf},
        ),
    ]


def _real_values(case: Any, choice: dict[str, Any] | None) -> Any:
    """Put a real record id, owner or envelope into a generated case, when one was drawn."""
    if not choice:
        return case
    method, path = case.operation.method.upper(), case.operation.path
    for name, value in choice.items():
        if name == "body" and (method, path) == ("POST", "/api/v1/records/"):
            case.body = value()
        elif name == "grantee" and (method, path) == ("POST", "/api/v1/grants/"):
            case.body = {"grantee": value}
        elif (method, path) == ("DELETE", "/api/v1/records/{record_id}/"):
            # Deleting the real records would leave every later case about them a 410
            # (tests/sharing/test_deletion.py covers deleting); random ids still reach it.
            continue
        elif case.path_parameters and name in case.path_parameters:
            case.path_parameters = {**case.path_parameters, name: value}
    return case


@pytest.fixture
def portal(live_server, make_robot, settings, django_capture_on_commit_callbacks):
    """Two owners with robots; one shares its records with the other; a few records."""
    settings.REST_FRAMEWORK = {
        **settings.REST_FRAMEWORK,
        "DEFAULT_THROTTLE_RATES": {"anon": None, "user": None, "upload": None},
    }
    alice, bob = make_robot("alice"), make_robot("bob")
    with django_capture_on_commit_callbacks(execute=True):
        grant_create(owner=bob.owner, grantee=alice.owner)
    from sharing.services.uploads import record_create_batch

    with django_capture_on_commit_callbacks(execute=True):
        records = record_create_batch(robot=alice.robot, envelopes=[alice.seal(s) for s in (1, 2)])
        records += record_create_batch(robot=bob.robot, envelopes=[bob.seal(1)])
    return live_server, alice, bob, [str(record.id) for record in records]


@pytest.mark.parametrize("shard", range(SHARDS))
def test_the_api_survives_a_fuzz_run_without_500_or_schema_violations(portal, shard):
    server, alice, bob, record_ids = portal
    schema = schemathesis.openapi.from_url(f"{server.url}/api/schema/?format=json")
    seqs = itertools.count(100)

    def one_envelope() -> dict[str, str]:
        return {"envelope": base64.b64encode(alice.seal(next(seqs))).decode()}

    def a_batch() -> dict[str, list[str]]:
        envelopes = [alice.seal(next(seqs)) for _ in range(3)]
        return {"envelopes": [base64.b64encode(data).decode() for data in envelopes]}

    choices: list[dict[str, Any] | None] = [None, None, None]
    choices += [{"record_id": record_id} for record_id in record_ids]
    choices += [{"grantee": name} for name in ("bob", bob.owner.eoa_address, "alice")]
    choices += [{"body": one_envelope}, {"body": a_batch}]
    failures: list[str] = []
    calls = 0
    identities = _identities(alice)
    operations = sorted(
        (result.ok() for result in schema.get_all_operations()),
        key=lambda operation: operation.definition.raw.get("operationId", operation.label),
    )
    mine = operations[shard::SHARDS]
    assert mine
    for operation in mine:
        for mode in (GenerationMode.POSITIVE, GenerationMode.NEGATIVE):
            calls += _fuzz(operation, mode, identities, server.url, choices, failures)
    assert not failures, "\n\n".join(failures[:5])
    assert calls > 600 // SHARDS


def _fuzz(
    operation: Any,
    mode: GenerationMode,
    identities: list[Identity],
    base_url: str,
    choices: list[dict[str, Any] | None],
    failures: list[str],
) -> int:
    """Each case drawn is sent as every identity: drawing the cases is most of the run's time
    (negative ones above all), and each identity's answers are checked as before."""
    calls = 0
    # Real values only where the case is meant to be valid: they would mend a negative one.
    mixed_in = choices if mode is GenerationMode.POSITIVE else [None]
    strategy = st.tuples(operation.as_strategy(generation_mode=mode), st.sampled_from(mixed_in))

    @given(drawn=strategy)
    @settings(
        max_examples=EXAMPLES_OF.get(
            operation.definition.raw.get("operationId"), EXAMPLES_PER_OPERATION
        ),
        deadline=None,
        database=None,
        derandomize=True,
        suppress_health_check=list(HealthCheck),
    )
    def run(drawn: tuple[Any, dict[str, Any] | None]) -> None:
        nonlocal calls
        for identity in identities:
            # Real values afresh for each identity: an envelope drawn is a new one each time.
            case = _real_values(*drawn)
            calls += 1
            try:
                case.call_and_validate(
                    base_url=base_url,
                    headers=identity.headers,
                    cookies=identity.cookies,
                    excluded_checks=_excluded_checks(operation, identity),
                )
            except FailureGroup as failure:  # keep going, report them all at the end
                label = f"{identity.name}, {mode.value}: {operation.label}"
                failures.append(f"{label}\n{failure}")

    try:
        run()
    except Unsatisfiable:
        # Nothing to make invalid (no parameters, no body): only positive cases exist.
        assert mode is GenerationMode.NEGATIVE, operation.label
    return calls


def _excluded_checks(operation: Any, identity: Identity) -> list[Callable]:
    from schemathesis.specs.openapi import checks

    # The stateful resource checks need links that the schema does not declare.
    excluded = [checks.use_after_free, checks.ensure_resource_availability]
    if identity.cookies:
        # It swaps in a made-up token but leaves our session cookie: a valid login, rightly
        # accepted (a proxy's Basic credentials beside a session must not lock browsers out).
        excluded.append(checks.ignored_auth)
    if operation.definition.raw.get("operationId") in (
        "records_upload",
        "grants_create",
        "grants_change",
        "robot_pairing_create",
        "exports_create",
        "exports_count",
        "records_series",
        "records_completeness",
        "access_log_list",
    ):
        # Valid by the schema yet refused with 400 by design: random bytes are no envelope
        # (`invalid_envelope`), granting oneself is `self_grant`, a random robot id is not the
        # owner's and a window before 1970 holds no capture (`invalid_grant_terms`), random hex
        # is no point on the SM2 curve (`invalid_pairing_request`), a random robot id or topic
        # selects no record (`invalid_selection`, also when only counted), and a period may
        # not end before it starts (`invalid_request`, a series' and a completeness window's
        # too) nor, for a series, be longer than SERIES_MAX_RANGE (`invalid_series`).
        excluded.append(checks.positive_data_acceptance)
    return excluded
