"""Static files (the vendored SM2 script the register page needs) are served without DEBUG."""

import pytest
from django.test import override_settings


@pytest.mark.django_db
@override_settings(DEBUG=False)
def test_vendored_sm2_script_is_served_without_debug(client):
    page = client.get("/register/")
    assert page.status_code == 200
    scripts = [
        line.split('src="', 1)[1].split('"', 1)[0]
        for line in page.content.decode().splitlines()
        if "<script" in line and 'src="' in line
    ]
    assert scripts
    for src in scripts:
        response = client.get(src)
        assert response.status_code == 200, src
        assert b"".join(response.streaming_content if response.streaming else [response.content])
