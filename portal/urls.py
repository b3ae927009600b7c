"""URL routes of the portal: its own pages, the apps' pages, the REST API, the admin console."""

from django.contrib import admin
from django.templatetags.static import static
from django.urls import include, path
from django.views.generic import RedirectView

from portal import views
from portal.csp_reports import CspReportView

# The API first: every robot upload and view is matched against these before the pages'.
urlpatterns = [
    path("api/", include("portal.api_urls")),
    path("", views.home, name="home"),
    path("dashboard/", views.dashboard, name="dashboard"),
    path("account/security/", views.security, name="security"),
    # Where browsers report what the Content-Security-Policy blocked (settings.CSP_REPORT_URL).
    path("csp-report/", CspReportView.as_view(), name="csp-report"),
    path("", include("accounts.urls")),
    path("", include("sharing.urls")),
    path("", include("alerts.urls")),
    path("admin/", admin.site.urls),
    # Browsers ask for /favicon.ico on pages that name no icon (the admin console's).
    path("favicon.ico", RedirectView.as_view(url=static("portal/favicon.svg"), permanent=True)),
]
