"""Bodies that only a real socket shows: too large, nested too deeply, not UTF-8."""

import pytest
import requests

from sharing.models import Record

pytestmark = pytest.mark.django_db(transaction=True)


def test_a_real_server_answers_hostile_bodies_with_json_errors(live_server, make_robot, settings):
    settings.DATA_UPLOAD_MAX_MEMORY_SIZE = 1024 * 1024
    setup = make_robot()
    url = f"{live_server.url}/api/v1/records/"
    headers = {"Authorization": f"Token {setup.token}", "Content-Type": "application/json"}
    bodies = [
        (b'{"envelope": "' + b"A" * (3 * 1024 * 1024) + b'"}', 413, "request_too_large"),
        (b"[" * 200_000 + b"]" * 200_000, 400, "malformed_request"),
        (b'{"envelope": "\xff\xfe"}', 400, "malformed_request"),
        (b"\x00" * 1000, 400, "malformed_request"),
    ]
    for body, status, error in bodies:
        answer = requests.post(url, data=body, headers=headers, timeout=30)
        assert answer.status_code == status, body[:40]
        assert answer.json()["error"] == error, body[:40]
    # The server is still there, and nothing was stored.
    assert requests.get(url, headers=headers, timeout=30).status_code == 200
    assert not Record.objects.exists()
