"""Template filters of the robot pages."""

from datetime import datetime

from django import template
from django.utils import timezone

from accounts.lastseen import seen_ago_text

register = template.Library()


@register.filter
def seen_ago(moment: datetime | None) -> str:
    """accounts.lastseen.seen_ago_text from now."""
    return seen_ago_text(moment, now=timezone.now())
