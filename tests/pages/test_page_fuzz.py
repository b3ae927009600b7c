"""Every page's query parameters, fuzzed as schemathesis fuzzes the API: no 500, and no
bare 400.

A signed-in owner with real records (odometry, an image), a grant and a robot asks every GET
page of the URL conf (the records' own pages with a real record id) with generated query
strings: the parameters the pages read and random names, each with strings of any Unicode,
numbers far past 64 bits, dates and times at the ends of the calendar with any UTC offset,
and the same name repeated. Every answer is under 500; a page that answers 400 says why
(a form's error list or a message), and a streamed download is read to its end.
"""

import re
import uuid
from urllib.parse import urlencode

import pytest
from django.urls import URLPattern, URLResolver, get_resolver
from django.urls.resolvers import RoutePattern
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from sharing.grant_terms import grant_terms_make
from sharing.services.grants import grant_create
from tests.pages.conftest import image, odometry

pytestmark = pytest.mark.django_db

# The names the pages read (sharing/forms.py, the paginators, ?change=, ?code=, ?direction=).
NAMES = [
    "since",
    "until",
    "page",
    "sort",
    "robot",
    "topic",
    "data_type",
    "status",
    "owner",
    "kind",
    "direction",
    "viewer",
    "verdict",
    "credential",
    "change",
    "grantee",
    "code",
    "next",
    "script",
    "lang",
]
# Routes that are no pages for a signed-in owner's GET: the API (fuzzed by tests/api), the
# admin console, signing out, and the report endpoint (tests/pages/test_csp.py).
SKIPPED = re.compile(r"^/(api/|admin/|logout/|csp-report/|favicon\.ico)")

_calendar_ends = st.sampled_from(
    [
        "0001-01-01T00:00:00+14:00",
        "0001-01-01T00:00",
        "0001-01-01",
        "9999-12-31T23:59:59-14:00",
        "9999-12-31T23:59:59.999999",
        "9999-12-31",
        "1970-01-01T00:00:00Z",
        "2038-01-19T03:14:08",
        "0000-00-00",
        "2026-02-30T25:61",
        "-0001-01-01",
        "+10000-01-01",
        "2026-03-01T12:00:00+99:99",
        "2026-03-01T12:00:00.1234567890123",
        "2026-03-01 12:00",
        "1e309",
        "NaN",
    ]
)
_datetimes = st.datetimes(
    timezones=st.sampled_from([None])
    | st.timezones()
    | st.just(__import__("datetime").timezone(__import__("datetime").timedelta(hours=14)))
).map(lambda moment: moment.isoformat())
_numbers = st.integers(min_value=-(10**40), max_value=10**40).map(str) | st.floats().map(str)
# No lone surrogates: they are no UTF-8 a browser could send.
_text = st.text(st.characters(exclude_categories=("Cs",)), max_size=300)
# Weighted towards what the pages read: their names, and times (the values most of them parse).
_values = st.one_of(_calendar_ends, _calendar_ends, _datetimes, _numbers, _text, st.just(""))
_names = st.one_of(
    st.sampled_from(["since", "until"]),
    st.sampled_from(NAMES),
    st.sampled_from(NAMES),
    st.text(st.characters(exclude_categories=("Cs",)), max_size=20),
)
_queries = st.lists(st.tuples(_names, _values), max_size=8)
# The pages whose query parameters are forms: asked more often than the rest.
FORM_PAGES = re.compile(r"^/(records/|shared/|audit/|access-log/|records/delete/|records/.+/)")


def _route(pattern: str, samples: dict[str, str]) -> str:
    return re.sub(r"<(?:(\w+):)?(\w+)>", lambda m: samples.get(m.group(2), "x"), pattern)


def _pages(resolver: URLResolver, prefix: str = "") -> list[str]:
    """The URL conf's route patterns, as written (`records/<uuid:record_id>/`)."""
    found = []
    for entry in resolver.url_patterns:
        if not isinstance(entry.pattern, RoutePattern):
            continue
        if isinstance(entry, URLResolver):
            found += _pages(entry, prefix + str(entry.pattern))
        elif isinstance(entry, URLPattern):
            found.append("/" + prefix + str(entry.pattern))
    return [page for page in found if not SKIPPED.match(page)]


@pytest.fixture
def owner_pages(client, make_robot, upload, settings):
    """The pages to fuzz, as paths, for a signed-in owner with records, a grant and a robot;
    no page rate limit and no budget of checks (the fuzz asks thousands of pages)."""
    settings.PAGE_RATE_USER = ""
    settings.CHECK_BUDGET = ""
    alice = make_robot("alice")
    bob = make_robot("bob")
    pose = upload(alice, 1, plaintext=odometry("alice", 1.0, 2.0), data_type="nav_msgs/Odometry")
    shot = upload(alice, 2, plaintext=image("alice"), topic="/cam", data_type="sensor_msgs/Image")
    upload(bob, 1)
    grant_create(
        owner=bob.owner,
        grantee=alice.owner,
        made_with="session",
        terms=grant_terms_make(owner=bob.owner),
    )
    client.force_login(alice.owner.user)
    samples_of = {
        "record_id": [str(pose.pk), str(shot.pk), str(uuid.uuid4())],
        "robot_id": [str(alice.robot.pk), str(bob.robot.pk), str(uuid.uuid4())],
        "export_id": [str(uuid.uuid4())],
        "token_id": ["1", "99999999999"],
        "endpoint_id": [str(uuid.uuid4())],
        "token": ["x" * 40],
    }
    paths = []
    for pattern in _pages(get_resolver()):
        names = re.findall(r"<(?:\w+:)?(\w+)>", pattern)
        if not names:
            paths.append(pattern)
            continue
        for n in range(max(len(samples_of.get(name, ["x"])) for name in names)):
            samples = {
                name: samples_of.get(name, ["x"])[n % len(samples_of.get(name, ["x"]))]
                for name in names
            }
            paths.append(_route(pattern, samples))
    assert "/records/" in paths
    assert f"/records/{pose.pk}/" in paths
    assert f"/records/{shot.pk}/gallery/" in paths
    paths = sorted(set(paths))
    return client, paths + [path for path in paths if FORM_PAGES.match(path)] * 2


def _says_why(html: str) -> bool:
    return any(
        mark in html for mark in ('class="errorlist', 'class="notice', "Left out of the filters")
    )


def test_no_page_answers_500_or_a_bare_400_to_any_query(owner_pages):
    client, paths = owner_pages

    @settings(
        max_examples=250,
        deadline=None,
        suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
        database=None,
    )
    @given(path=st.sampled_from(paths), query=_queries)
    def ask(path: str, query: list[tuple[str, str]]) -> None:
        url = f"{path}?{urlencode(query)}" if query else path
        answer = client.get(url)
        if answer.streaming:
            b"".join(answer.streaming_content)
        assert answer.status_code < 500, (url, answer.status_code)
        content_type = answer.headers.get("Content-Type", "")
        if answer.status_code == 400 and content_type.startswith("text/html"):
            assert _says_why(answer.content.decode()), url

    ask()


HARD_QUERIES = [
    [(name, "a\x00b") for name in NAMES],
    [(name, "9" * 40) for name in NAMES],
    [(name, "0001-01-01T00:00:00+14:00") for name in NAMES],
    [(name, "9999-12-31T23:59:59-14:00") for name in NAMES],
    [(name, "\u202e\U0001f916" * 200) for name in NAMES],
    [("since", "2026-03-02"), ("since", "x"), ("until", "2026-03-01"), ("page", "-1")],
]


def test_hard_values_on_every_page(owner_pages):
    """The values that broke pages before, on every page at once (no luck needed)."""
    client, paths = owner_pages
    for path in sorted(set(paths)):
        for query in HARD_QUERIES:
            answer = client.get(f"{path}?{urlencode(query)}")
            if answer.streaming:
                b"".join(answer.streaming_content)
            assert answer.status_code < 500, (path, query[0])
            if answer.status_code == 400 and answer["Content-Type"].startswith("text/html"):
                assert _says_why(answer.content.decode()), (path, query[0])
