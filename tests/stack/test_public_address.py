"""`make run` for robots on the same network: PORTAL_HOST=0.0.0.0 with PORTAL_PUBLIC_URL
listens on every address and allows the public URL's host beside loopback's; the banner says
where to pair; a wildcard address without a public URL is refused before anything starts."""

import pytest
from django.test import Client, override_settings

from stack.run import Stack, StackConfig, main

PUBLIC = "http://192.168.1.10:8000"
EVERY_ADDRESS = "0.0.0.0"  # noqa: S104


def stack_of(tmp_path, **environ: str) -> Stack:
    return Stack(StackConfig.from_environment({"AUTHROS_VAR_DIR": str(tmp_path), **environ}))


def test_the_public_urls_host_is_allowed_beside_loopback(tmp_path, monkeypatch):
    monkeypatch.delenv("DJANGO_ALLOWED_HOSTS", raising=False)
    stack = stack_of(tmp_path, PORTAL_HOST=EVERY_ADDRESS, PORTAL_PUBLIC_URL=PUBLIC + "/")
    env = stack.environment()
    assert env["DJANGO_ALLOWED_HOSTS"] == "localhost,127.0.0.1,[::1],192.168.1.10"
    assert stack.public_url == PUBLIC
    assert stack.web_url == "http://127.0.0.1:8000"  # the stack's own checks stay on loopback
    banner = stack.banner()
    assert f"Portal:        {PUBLIC}/" in banner
    assert f"authros-agent pair --portal {PUBLIC} --name NAME" in banner
    assert "192.168.1.10" in banner.split("Allowed hosts:")[1].splitlines()[0]
    # every link it prints opens from another machine
    assert f"Admin console: {PUBLIC}/admin/" in banner
    assert f"API docs:      {PUBLIC}/api/docs/" in banner
    assert stack._listening() == f"0.0.0.0:8000, reached at {PUBLIC}/"


def test_loopback_stays_the_default_and_the_banner_says_how_to_listen_beyond(tmp_path, monkeypatch):
    monkeypatch.delenv("DJANGO_ALLOWED_HOSTS", raising=False)
    stack = stack_of(tmp_path)
    assert stack.environment()["DJANGO_ALLOWED_HOSTS"] == "localhost,127.0.0.1,[::1]"
    assert "PORTAL_HOST=0.0.0.0 PORTAL_PUBLIC_URL=http://ADDRESS:PORT make run" in stack.banner()


def test_a_specific_address_and_an_ipv6_public_url_are_allowed_as_django_spells_them(
    tmp_path, monkeypatch
):
    monkeypatch.delenv("DJANGO_ALLOWED_HOSTS", raising=False)
    stack = stack_of(tmp_path, PORTAL_HOST="10.0.0.5", PORTAL_PUBLIC_URL="http://[fd00::5]:8000")
    assert stack.allowed_hosts == ["localhost", "127.0.0.1", "[::1]", "10.0.0.5", "[fd00::5]"]


def test_an_operators_own_allowed_hosts_are_kept(tmp_path, monkeypatch):
    monkeypatch.setenv("DJANGO_ALLOWED_HOSTS", "portal.example.org")
    stack = stack_of(tmp_path, PORTAL_HOST=EVERY_ADDRESS, PORTAL_PUBLIC_URL=PUBLIC)
    assert stack.environment()["DJANGO_ALLOWED_HOSTS"] == "portal.example.org"


@pytest.mark.django_db
def test_the_portal_answers_a_robot_on_the_network_and_refuses_other_hosts(tmp_path, monkeypatch):
    monkeypatch.delenv("DJANGO_ALLOWED_HOSTS", raising=False)
    allowed = stack_of(tmp_path, PORTAL_HOST=EVERY_ADDRESS, PORTAL_PUBLIC_URL=PUBLIC).allowed_hosts
    with override_settings(ALLOWED_HOSTS=allowed):
        assert Client().get("/admin/login/", HTTP_HOST="192.168.1.10:8000").status_code == 200
        assert Client().get("/admin/login/", HTTP_HOST="192.168.1.11:8000").status_code == 400


@pytest.mark.parametrize(
    ("argv", "said"),
    [
        (["--host", EVERY_ADDRESS], "PORTAL_PUBLIC_URL=http://ADDRESS:PORT"),
        (["--host", EVERY_ADDRESS, "--public-url", "192.168.1.10:8000"], "http:// or https://"),
    ],
)
def test_listening_beyond_loopback_without_a_public_url_is_refused_at_once(argv, said, capsys):
    with pytest.raises(SystemExit) as exit_:
        main(["run", *argv])
    assert exit_.value.code == 2
    assert said in capsys.readouterr().err
