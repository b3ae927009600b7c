"""The `outcome_text` filter: a verdict's outcome code (as an export's left-out list keeps it)
in the words the record pages use (Verdict.Outcome's labels)."""

from django import template

from sharing.models import Verdict

register = template.Library()


@register.filter
def outcome_text(code: str) -> str:
    """Verdict.Outcome's label of `code` ("not_anchored_yet": "not anchored yet"); an unknown
    code as it is."""
    try:
        return Verdict.Outcome(code).label
    except ValueError:
        return code
