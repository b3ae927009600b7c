"""URL routes of the portal: its own pages, the apps' pages, the REST API, the admin console."""

from django.contrib import admin
from django.urls import include, path

from portal import views

# The API first: every robot upload and view is matched against these before the pages'.
urlpatterns = [
    path("api/", include("portal.api_urls")),
    path("", views.home, name="home"),
    path("dashboard/", views.dashboard, name="dashboard"),
    path("account/security/", views.security, name="security"),
    path("", include("accounts.urls")),
    path("", include("sharing.urls")),
    path("", include("alerts.urls")),
    path("admin/", admin.site.urls),
]
