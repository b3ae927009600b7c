"""Times typed beside "(UTC)" are 24-hour text, whatever the browser's locale (issue 35): a
datetime-local input showed "02:30 PM" in an en-US Chromium beside a "(UTC)" label."""

from datetime import UTC, datetime

from sharing.forms import GrantForm


def test_time_fields_are_24_hour_text_and_read_both_forms():
    form = GrantForm(robots=[], topics=[], initial={"expires_at": datetime(2026, 5, 1, 14, 30)})
    html = str(form["expires_at"])
    assert 'type="text"' in html
    assert 'value="2026-05-01 14:30"' in html
    assert 'placeholder="YYYY-MM-DD HH:MM"' in html
    assert "datetime-local" not in html
    assert "(UTC)" in form["expires_at"].label
    for typed in ("2026-01-01 14:30", "2026-01-01T14:30"):
        bound = GrantForm({"grantee": "bob", "since": typed}, robots=[], topics=[])
        assert bound.is_valid(), bound.errors
        assert bound.cleaned_data["since"] == datetime(2026, 1, 1, 14, 30, tzinfo=UTC)
    refused = GrantForm({"grantee": "bob", "since": "2 pm"}, robots=[], topics=[])
    assert not refused.is_valid()
    assert "24-hour, UTC" in refused.errors["since"][0]
