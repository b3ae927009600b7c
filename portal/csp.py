"""The portal's Content-Security-Policy: the header every answer carries.

The pages run SM2 in the browser on a key the owner types or generates, so no script may run
but the portal's own static files: no inline <script>, no on*= handler, no style attribute
(settings.CSP_DIRECTIVES; portal.middleware.ContentSecurityPolicyMiddleware sets the header).
Browsers send what they blocked to settings.CSP_REPORT_URL (portal.csp_reports), named by
`report-uri` alone: with `report-to` beside it Chromium ignores `report-uri` and sends its
reports batched, about a minute later, where `report-uri` sends each one as it happens.
"""

from django.conf import settings


def content_security_policy() -> str:
    """The header's value: settings.CSP_DIRECTIVES and where to report."""
    directives = [
        f"{name} {' '.join(sources)}" for name, sources in settings.CSP_DIRECTIVES.items()
    ]
    directives.append(f"report-uri {settings.CSP_REPORT_URL}")
    return "; ".join(directives)
