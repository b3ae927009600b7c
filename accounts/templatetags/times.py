"""The `utc` filter: a moment in the owner's words on every page (core.times.utc_text):
`{% load times %}` then `{{ record.captured_at|utc }}` gives "2026-12-01 21:46:00 UTC"."""

from datetime import datetime

from django import template

from core.times import utc_text

register = template.Library()


@register.filter
def utc(moment: datetime | str | None) -> str:
    """core.times.utc_text."""
    return utc_text(moment)
