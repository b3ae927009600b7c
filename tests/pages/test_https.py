"""The HTTPS switch (AUTHROS_HTTPS): secure cookies, HSTS and the proxy's scheme header.

portal/settings.py reads the environment once, at import, so each case imports it afresh in
a subprocess with the variable set.
"""

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
from django.conf import settings as django_settings

pytestmark = pytest.mark.process

SHOWN = (
    "SESSION_COOKIE_SECURE",
    "CSRF_COOKIE_SECURE",
    "SECURE_SSL_REDIRECT",
    "SECURE_HSTS_SECONDS",
    "SECURE_PROXY_SSL_HEADER",
)


def _settings_with(tmp_path: Path, https: str | None) -> dict[str, object]:
    env = {
        name: value
        for name, value in os.environ.items()
        if name != "AUTHROS_HTTPS" and name != "DJANGO_SETTINGS_MODULE"
    }
    # Secrets the import would otherwise create under var/.
    env.update({"DJANGO_SECRET_KEY": "x" * 50, "AUTHROS_VAR_DIR": str(tmp_path)})
    if https is not None:
        env["AUTHROS_HTTPS"] = https
    script = (
        "import json, portal.settings as s; "
        f"print(json.dumps({{name: getattr(s, name) for name in {SHOWN!r}}}))"
    )
    done = subprocess.run(
        [sys.executable, "-c", script],
        cwd=django_settings.BASE_DIR,
        env=env,
        capture_output=True,
        text=True,
        timeout=60,
        check=True,
    )
    return json.loads(done.stdout.strip().splitlines()[-1])


def test_https_on_makes_cookies_secure_and_sets_hsts(tmp_path):
    values = _settings_with(tmp_path, "1")
    assert values["SESSION_COOKIE_SECURE"] is True
    assert values["CSRF_COOKIE_SECURE"] is True
    assert values["SECURE_SSL_REDIRECT"] is True
    assert values["SECURE_HSTS_SECONDS"] >= 31536000
    assert values["SECURE_PROXY_SSL_HEADER"] == ["HTTP_X_FORWARDED_PROTO", "https"]


@pytest.mark.parametrize("https", [None, "0"])
def test_https_off_trusts_no_scheme_header(tmp_path, https):
    values = _settings_with(tmp_path, https)
    assert values == {
        "SESSION_COOKIE_SECURE": False,
        "CSRF_COOKIE_SECURE": False,
        "SECURE_SSL_REDIRECT": False,
        "SECURE_HSTS_SECONDS": 0,
        "SECURE_PROXY_SSL_HEADER": None,
    }
