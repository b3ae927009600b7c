"""Times as the pages say them to owners: UTC, to the second, no microseconds, the zone named
("2026-12-01 21:46:00 UTC"). One function, so that every page and message says a moment the
same way (the `utc` template filter of accounts/templatetags/times.py is this)."""

from datetime import UTC, datetime

UTC_TEXT = "%Y-%m-%d %H:%M:%S UTC"


def utc_text(moment: datetime | str | None) -> str:
    """The moment in the owner's words; an ISO 8601 text (as a stored selection keeps its
    range) is read first. A naive datetime is taken as UTC (the project's TIME_ZONE); "" for
    None, and a text that is no moment comes back as it is."""
    if moment is None or moment == "":
        return ""
    if isinstance(moment, str):
        try:
            moment = datetime.fromisoformat(moment.replace("Z", "+00:00"))
        except ValueError:
            return moment
    if moment.tzinfo is not None:
        moment = moment.astimezone(UTC)
    return moment.strftime(UTC_TEXT)
