"""What every owner page wraps itself in: the owner check and the no-cache answer.

Kept apart from the views so that the pages of every app (and the project's own) use them
without importing one another's views.
"""

from collections.abc import Callable
from functools import wraps

from django.contrib.auth.decorators import login_required
from django.http import HttpRequest, HttpResponse
from django.shortcuts import render

from accounts.selectors import owner_for_user

OwnerView = Callable[..., HttpResponse]


def owner_required(view: OwnerView) -> OwnerView:
    """Login required, and the user must be an owner: sets `request.owner`.

    Operator accounts (admin users without an owner) get a page pointing to the admin.
    """

    @wraps(view)
    @login_required
    def wrapped(request: HttpRequest, *args: object, **kwargs: object) -> HttpResponse:
        owner = owner_for_user(request.user)
        if owner is None:
            return render(request, "accounts/not_an_owner.html", status=403)
        request.owner = owner
        return view(request, *args, **kwargs)

    return wrapped


def no_store(response: HttpResponse) -> HttpResponse:
    """Keep a page that shows a secret or decrypted data out of every cache."""
    response["Cache-Control"] = "no-store, private"
    response["Pragma"] = "no-cache"
    return response
