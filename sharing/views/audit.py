"""The audit trail page: the owner's transactions and the anchoring of their records."""

from django.http import HttpRequest, HttpResponse
from django.shortcuts import render
from django.views.decorators.http import require_GET

from accounts.decorators import owner_required, page_throttle
from accounts.models import Owner
from sharing.audit import audit_page_of_owner
from sharing.forms import AuditFilterForm
from sharing.views.filters import say_left_out

# Minutes of anchoring on one page of the audit trail.
AUDIT_ENTRIES_PER_PAGE = 50


@owner_required
@page_throttle()
@require_GET
def audit(request: HttpRequest) -> HttpResponse:
    owner: Owner = request.owner
    form = AuditFilterForm(request.GET or None, owner=owner)
    say_left_out(request, form)
    trail = audit_page_of_owner(
        owner, page=request.GET.get("page"), per_page=AUDIT_ENTRIES_PER_PAGE, **form.filters()
    )
    context = {
        "form": form,
        "trail": trail,
        "page": trail.anchoring,
        "owner": owner,
        "filtered": bool(form.filters()),
    }
    return render(request, "sharing/audit.html", context)
