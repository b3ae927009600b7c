"""The portal's Content-Security-Policy: the header every answer carries.

The pages run SM2 in the browser on a key the owner types or generates, so no script may run
but the portal's own static files: no inline <script>, no on*= handler, no style attribute
(settings.CSP_DIRECTIVES; portal.middleware.ContentSecurityPolicyMiddleware sets the header).
Browsers send what they blocked to settings.CSP_REPORT_URL (portal.csp_reports), named both
by `report-uri` and by `report-to` (with the Reporting-Endpoints header).
"""

from django.conf import settings

# The name `report-to` gives the endpoint in the Reporting-Endpoints header.
CSP_REPORT_GROUP = "csp"


def content_security_policy() -> str:
    """The header's value: settings.CSP_DIRECTIVES and where to report."""
    directives = [
        f"{name} {' '.join(sources)}" for name, sources in settings.CSP_DIRECTIVES.items()
    ]
    directives.append(f"report-uri {settings.CSP_REPORT_URL}")
    directives.append(f"report-to {CSP_REPORT_GROUP}")
    return "; ".join(directives)


def reporting_endpoints() -> str:
    """The Reporting-Endpoints header that names `report-to`'s endpoint."""
    return f'{CSP_REPORT_GROUP}="{settings.CSP_REPORT_URL}"'
