"""The Content-Security-Policy (portal/csp.py): on every answer of every route, no inline
script or style in any template or rendered page, and the report endpoint (bounded,
sanitised, rate-limited, never a 500 on junk)."""

import json
import logging
import re
import uuid
from html.parser import HTMLParser
from pathlib import Path

import pytest
from django.conf import settings
from django.template import engines
from django.urls import URLPattern, URLResolver, get_resolver, reverse
from django.urls.resolvers import RoutePattern

from tests.support.logs import logged_by

pytestmark = pytest.mark.django_db

TEMPLATES = Path(settings.BASE_DIR) / "templates"
REPORT = "/csp-report/"
_SAMPLES = {"uuid": str(uuid.uuid4()), "int": "1", "str": "x", "slug": "x", "path": "x"}


def _policy(response) -> dict[str, str]:
    header = response.headers["Content-Security-Policy"]
    directives = [part.strip().split(None, 1) for part in header.split(";")]
    return {name: value for name, value in directives}


def test_the_policy_is_strict():
    from django.test import Client

    policy = _policy(Client().get(reverse("login")))
    assert policy["default-src"] == "'self'"
    assert policy["script-src"] == "'self'"
    assert policy["style-src"] == "'self'"
    assert policy["img-src"] == "'self' data:"
    assert policy["object-src"] == "'none'"
    assert policy["base-uri"] == "'none'"
    assert policy["frame-ancestors"] == "'none'"
    assert policy["form-action"] == "'self'"
    assert policy["report-uri"] == REPORT == reverse("csp-report") == settings.CSP_REPORT_URL
    assert "report-to" not in policy
    assert "unsafe" not in " ".join(policy.values())


def _page_routes(resolver: URLResolver, prefix: str = "") -> list[str]:
    """A path for every route of the URL conf: its parameters filled with a sample value;
    regular-expression routes (the admin's, the API's catch-all) with no group as written."""
    paths = []
    for entry in resolver.url_patterns:
        pattern = entry.pattern
        if isinstance(pattern, RoutePattern):
            route = re.sub(
                r"<(?:(\w+):)?\w+>", lambda m: _SAMPLES[m.group(1) or "str"], str(pattern)
            )
        else:
            regex = str(pattern).lstrip("^").rstrip("$").rstrip("\\Z")
            if re.search(r"[()\[\]*+?|\\]", regex):
                continue
            route = regex
        if isinstance(entry, URLResolver):
            paths += _page_routes(entry, prefix + route)
        elif isinstance(entry, URLPattern):
            paths.append("/" + prefix + route)
    return sorted(set(paths))


class _InlineFinder(HTMLParser):
    """Inline scripts, event handler attributes, style attributes and <style> elements."""

    def __init__(self) -> None:
        super().__init__()
        self.found: list[str] = []
        self._in: str | None = None

    def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        names = {name.lower(): value or "" for name, value in attrs}
        if tag == "script" and "src" not in names:
            self.found.append(f"<script> without src: {self.getpos()}")
        if tag == "style":
            self.found.append(f"<style>: {self.getpos()}")
        self._in = tag if tag == "script" else None
        for name, value in names.items():
            if name.startswith("on"):
                self.found.append(f"{name}= on <{tag}>: {self.getpos()}")
            if name == "style":
                self.found.append(f"style= on <{tag}>: {self.getpos()}")
            if name in ("href", "src", "action") and value.strip().lower().startswith(
                "javascript:"
            ):
                self.found.append(f"javascript: URL on <{tag}>: {self.getpos()}")

    def handle_data(self, data: str) -> None:
        if self._in == "script" and data.strip():
            self.found.append(f"a <script src> with a body: {self.getpos()}")

    def handle_endtag(self, tag: str) -> None:
        self._in = None


def inline_code(html: str) -> list[str]:
    finder = _InlineFinder()
    finder.feed(html)
    finder.close()
    return finder.found


def test_no_template_has_inline_script_or_style():
    checked = 0
    for path in sorted(TEMPLATES.rglob("*")):
        if path.suffix not in (".html", ".svg") or not path.is_file():
            continue
        source = path.read_text()
        # Template tags may stand where attributes are: parse the text between them.
        text = re.sub(r"{% comment %}.*?{% endcomment %}|{#.*?#}", "", source, flags=re.S)
        found = inline_code(re.sub(r"{%.*?%}|{{.*?}}", "", text, flags=re.S))
        assert found == [], (str(path.relative_to(TEMPLATES)), found)
        checked += 1
    assert checked > 40
    # The finder finds what it is for.
    assert inline_code('<form onsubmit="return x()"></form>')
    assert inline_code("<script>alert(1)</script>")
    assert inline_code('<p style="color:red">')
    assert inline_code('<a href="javascript:alert(1)">')
    assert not inline_code('<script src="/static/portal/confirm.js" defer></script>')


def test_every_route_answers_with_the_policy_and_renders_no_inline_script(client, pending_owner):
    owner = pending_owner()
    owner.user.is_staff = owner.user.is_superuser = True
    owner.user.save()
    client.force_login(owner.user)
    expected = _policy(client.get(reverse("login")))
    routes = _page_routes(get_resolver())
    assert {"/records/", "/admin/", "/api/docs/", "/account/key/"} <= set(routes)
    pages = 0
    for route in routes:
        response = client.get(route)
        assert response.status_code < 500, (route, response.status_code)
        assert _policy(response) == expected, route
        content_type = response.headers.get("Content-Type", "")
        if content_type.startswith("text/html") and not response.streaming:
            assert inline_code(response.content.decode()) == [], route
            pages += 1
    assert pages > 30
    # Static files and refusals too.
    assert _policy(client.get("/static/portal/portal.css")) == expected
    assert _policy(client.get("/no-such-page/")) == expected
    client.logout()
    assert _policy(client.get(reverse("records"))) == expected


def test_the_api_docs_run_their_script_from_a_file(client):
    page = client.get("/api/docs/")
    assert page.status_code == 200
    assert inline_code(page.content.decode()) == []
    script = re.search(r'<script src="([^"]*script[^"]*)"', page.content.decode()).group(1)
    code = client.get(script.replace("&amp;", "&"))
    assert code.status_code == 200
    assert code.headers["Content-Type"].startswith("application/javascript")
    assert b"/api/schema/" in code.content


def test_the_error_pages_carry_no_inline_style():
    for name in ("500.html", "503_misconfigured.html"):
        html = engines["django"].get_template(name).render({"problems": ["x"]})
        assert inline_code(html) == [], name
        assert "portal/portal.css" in html


# --- the report endpoint ----------------------------------------------------------------------


def _violation(**extra: object) -> dict:
    return {
        "document-uri": "http://127.0.0.1:8000/account/key/?token=secret#frag",
        "violated-directive": "script-src-elem",
        "effective-directive": "script-src-elem",
        "blocked-uri": "inline",
        "source-file": "http://127.0.0.1:8000/account/key/",
        "line-number": 12,
        "script-sample": "alert(1)",
        **extra,
    }


def test_a_report_is_logged_sanitised(client):
    with logged_by("portal.csp_reports") as logs:
        answer = client.post(
            REPORT,
            json.dumps({"csp-report": _violation(**{"blocked-uri": "evil\u202e\r\nFAKE LINE"})}),
            content_type="application/csp-report",
        )
    assert answer.status_code == 204
    [entry] = [record for record in logs if record.levelno == logging.WARNING]
    text = entry.getMessage()
    assert "script-src-elem" in text
    assert "/account/key/" in text
    for hidden in ("secret", "frag", "\r", "\n", "\u202e"):
        assert hidden not in text
    assert "evil___FAKE LINE" in text


@pytest.mark.parametrize(
    ("body", "content_type", "status"),
    [
        (b"", "application/csp-report", 400),
        (b"not json", "application/csp-report", 400),
        (b"{}", "application/csp-report", 400),
        (b"[]", "application/reports+json", 400),
        (b'[{"type": "csp-violation", "body": {}}]', "application/reports+json", 400),
        (b'{"csp-report": "x"}', "application/json", 400),
        (b'{"csp-report": {"line-number": {"a": [1]}, "blocked-uri": null}}', "text/plain", 204),
        (b"[" * 100_000, "application/json", 413),
        (
            b'{"csp-report": {"blocked-uri": "' + b"a" * 20_000 + b'"}}',
            "application/csp-report",
            413,
        ),
        (b"\xff\xfe\x00", "application/csp-report", 400),
        (b"[" * 5000 + b"]" * 5000, "application/json", 400),
    ],
)
def test_junk_is_refused_never_a_500(client, body, content_type, status):
    answer = client.post(REPORT, body, content_type=content_type)
    assert answer.status_code == status, answer.content


def test_only_post(client):
    assert client.get(REPORT).status_code == 405


def test_reports_are_rate_limited_per_address(client, settings):
    rates = settings.REST_FRAMEWORK["DEFAULT_THROTTLE_RATES"]
    settings.REST_FRAMEWORK = {
        **settings.REST_FRAMEWORK,
        "DEFAULT_THROTTLE_RATES": {**rates, "csp_report": "3/minute"},
    }
    body = json.dumps({"csp-report": _violation()})
    answers = [
        client.post(REPORT, body, content_type="application/csp-report").status_code
        for _ in range(5)
    ]
    assert answers == [204, 204, 204, 429, 429]
    other = client.post(REPORT, body, content_type="application/csp-report", REMOTE_ADDR="10.9.8.7")
    assert other.status_code == 204
