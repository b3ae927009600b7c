"""The API docs (Swagger UI at /api/docs/) load only the portal's own static files: no CDN,
so they work offline and behind a strict firewall."""

import re

import pytest
from django.test import override_settings

pytestmark = pytest.mark.django_db


@override_settings(DEBUG=False)
def test_swagger_ui_loads_only_same_origin_static_files_and_they_are_served(client):
    page = client.get("/api/docs/")
    assert page.status_code == 200
    html = page.content.decode()
    # Without the page's CSRF token, whose 64 random letters and digits can hold "cdn".
    assert "cdn" not in re.sub(r'"[A-Za-z0-9]{64}"', '""', html).lower()
    assets = re.findall(r'<(?:script|link)\b[^>]*\b(?:src|href)="([^"]+)"', html)
    assert any(asset.endswith("swagger-ui-bundle.js") for asset in assets), assets
    assert any(asset.endswith("swagger-ui.css") for asset in assets), assets
    # Its own script comes from the page's address (`?script`): no inline script under the
    # Content-Security-Policy.
    [script] = [asset for asset in assets if "script" in asset.split("?", 1)[-1]]
    assert script.startswith("/api/docs/?")
    assert 'url: "/api/schema/"' in client.get(script.replace("&amp;", "&")).content.decode()
    for asset in assets:
        if asset == script:
            continue
        assert asset.startswith("/static/"), asset
        response = client.get(asset)
        assert response.status_code == 200, asset
        body = b"".join(response.streaming_content if response.streaming else [response.content])
        assert body, asset
    assert client.get("/api/schema/").status_code == 200
