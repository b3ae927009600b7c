"""The portal's front page: it only sends each visitor where they belong.

Every page but registration and sign-in needs a login, so anonymous visitors go to the
sign-in page; nothing here calls the chain or tells how the portal is deployed (operators
see the chain's status in the admin console).
"""

from django.http import HttpRequest, HttpResponse
from django.shortcuts import redirect

from accounts.selectors import owner_for_user


def home(request: HttpRequest) -> HttpResponse:
    if not request.user.is_authenticated:
        return redirect("login")
    if owner_for_user(request.user) is None and request.user.is_staff:
        return redirect("admin:index")
    # Owners, and accounts that are neither (the dashboard tells them they are no owner).
    return redirect("dashboard")
