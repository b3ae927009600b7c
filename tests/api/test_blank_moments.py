"""A window's bound sent blank in a query (`until=`) is refused 400, not taken as no bound: the
schema says a moment is ISO 8601, and what it calls invalid is answered as invalid (found by
the API fuzz run on exports/count). Left out, a bound is still no bound."""

import pytest

pytestmark = pytest.mark.django_db

ENDPOINTS = ("/api/v1/exports/count/", "/api/v1/records/completeness/", "/api/v1/access-log/")


@pytest.mark.parametrize("path", ENDPOINTS)
@pytest.mark.parametrize("bound", ["since", "until"])
def test_a_blank_bound_is_refused_and_a_missing_one_is_no_bound(path, bound, make_owner, owner_api):
    api = owner_api(make_owner("alice"))
    blank = api.get(f"{path}?{bound}=")
    assert blank.status_code == 400, blank.content
    assert bound in blank.json()["detail"]
    assert api.get(path).status_code == 200
