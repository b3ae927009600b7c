"""Times in the owner's words (core/times.py, the `utc` filter): UTC, seconds, no microseconds."""

from datetime import UTC, datetime, timedelta, timezone

import pytest
from django.template import Context, Template

from core.times import utc_text

pytestmark = pytest.mark.nodb


def test_a_moment_is_utc_to_the_second_with_the_zone_named():
    moment = datetime(2026, 12, 1, 21, 46, 0, 123456, tzinfo=UTC)
    assert utc_text(moment) == "2026-12-01 21:46:00 UTC"
    # Another zone is said in UTC, a naive one is taken as UTC (the project's TIME_ZONE).
    paris = moment.astimezone(timezone(timedelta(hours=1)))
    assert utc_text(paris) == "2026-12-01 21:46:00 UTC"
    assert utc_text(moment.replace(tzinfo=None)) == "2026-12-01 21:46:00 UTC"


def test_a_stored_iso_text_reads_as_the_same_words():
    # How a stored selection keeps its range, which the export page showed raw.
    assert utc_text("2026-12-01T21:46:00.000000Z") == "2026-12-01 21:46:00 UTC"
    assert utc_text("2026-12-01T22:46:00+01:00") == "2026-12-01 21:46:00 UTC"
    assert utc_text(None) == ""
    assert utc_text("") == ""
    assert utc_text("not a time") == "not a time"


def test_the_template_filter_is_the_same_function():
    template = Template("{% load times %}{{ at|utc }}")
    at = datetime(2026, 12, 1, 21, 46, 0, 999999, tzinfo=UTC)
    assert template.render(Context({"at": at})) == "2026-12-01 21:46:00 UTC"
