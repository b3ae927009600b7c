"""What a list page (records, audit, access log) says of the filters it left out."""

from django.contrib import messages
from django.http import HttpRequest

from sharing.forms import PeriodFilterForm


def say_left_out(request: HttpRequest, form: PeriodFilterForm) -> None:
    """A list page answers with the filters that hold; this says which were left out."""
    if said := form.left_out():
        messages.warning(request, said)
