"""What a new owner reads first says what exists: the README opens with `make run` and
`make test`, then a quickstart on the first screen whose install and commands are the
package's own; the robots page says how to install the agent and pair it, with the
command's real name and options."""

import re
import sys
import tomllib

import pytest
from django.urls import reverse

from authros_verify.__main__ import main as verify_main
from ros_agent.__main__ import main as agent_main
from tests.support.harness import REPO_ROOT

PYPROJECT = tomllib.loads((REPO_ROOT / "pyproject.toml").read_text())["project"]
FIRST_SCREEN = 45  # lines
# The project is not on PyPI: its install commands name the wheel built from this repository,
# each into a virtual environment made on the same screen, after the role's locked set.
INSTALL = re.compile(
    r"(\S+)/bin/pip install --no-deps \./(?:dist/)?([a-z_]+)-([0-9.]+)-py3-none-any\.whl"
)
LOCKED = re.compile(r"(\S+)/bin/pip install --require-hashes -r requirements/([a-z0-9_-]+)\.txt")
VENV = re.compile(r"python3 -m venv (?:--system-site-packages )?(\S+)")
WHEEL = (PYPROJECT["name"].replace("-", "_"), PYPROJECT["version"])


def _options(main, argv: list[str], capsys) -> str:
    with pytest.raises(SystemExit) as exit_:
        main(argv)
    assert exit_.value.code == 0
    return capsys.readouterr().out


def test_the_readme_opens_with_the_two_commands_then_the_quickstart():
    lines = (REPO_ROOT / "README.md").read_text().splitlines()
    assert lines[2] == "```sh"
    assert lines[3].startswith("make run ")
    assert lines[4].startswith("make test ")
    first_screen = "\n".join(lines[:FIRST_SCREEN])
    assert "## Quickstart" in first_screen
    for step in ("Run it", "Log in", "Pair a robot", "Share", "Export and verify"):
        assert f"**{step}" in first_screen, step


def installs_of(text: str) -> list[tuple[str, str]]:
    """(virtual environment, locked set) of each install in the text, each checked to be the
    wheel's, into a virtual environment the text makes, after that role's locked set; no
    bare `pip install` and no name of the project on PyPI, which nobody here owns."""
    venvs = VENV.findall(text)
    locked = LOCKED.findall(text)
    wheels = INSTALL.findall(text)
    assert [(venv, *WHEEL) for venv, _ in locked] == wheels
    assert {venv for venv, _ in locked} <= set(venvs)
    assert all((REPO_ROOT / "requirements" / f"{role}.txt").is_file() for _, role in locked)
    assert not re.search(r"(?<!/bin/)\bpip install", text.replace("python -m pip wheel", ""))
    assert f"{PYPROJECT['name']}[" not in text
    return locked


def test_the_quickstarts_commands_are_the_packages(capsys):
    first_screen = "\n".join((REPO_ROOT / "README.md").read_text().splitlines()[:FIRST_SCREEN])
    assert installs_of(first_screen) == [
        ("~/authros-agent", "agent"),
        ("~/authros-verify", "verify"),
    ]
    assert "pip wheel --no-deps -w dist ." in first_screen  # how the wheel is made
    assert "PORTAL_HOST=0.0.0.0" in first_screen  # how robots on the network reach it
    assert "PORTAL_PUBLIC_URL=http://ADDRESS:8000" in " ".join(first_screen.split())
    for command in ("authros-agent pair", "authros-agent --config", "authros-verify"):
        assert command in first_screen
        assert command.split()[0] in PYPROJECT["scripts"]
    pair = _options(agent_main, ["pair", "--help"], capsys)
    assert "--portal PORTAL" in pair
    assert "--name NAME" in pair
    verify = _options(verify_main, ["--help"], capsys)
    for option in ("--mcap", "--rpc", "--contract"):
        assert option in verify


@pytest.mark.django_db
def test_the_robots_page_says_how_to_install_the_agent_and_pair_it(client, make_owner):
    client.force_login(make_owner("alice").user)
    page = client.get(reverse("robots")).content.decode()
    assert installs_of(page) == [("~/authros-agent", "agent")]
    assert "authros-agent pair --portal http://testserver --name NAME" in page


def test_the_ros1_agent_without_rospy_says_how_to_get_it(monkeypatch, capsys):
    """A robot without Debian's rospy (or a virtual environment that cannot see it) is told
    what to install, or to run the ROS 2 agent, instead of a traceback."""
    monkeypatch.delitem(sys.modules, "ros_agent.node", raising=False)
    monkeypatch.setitem(sys.modules, "rospy", None)  # `import rospy` fails as when missing
    assert agent_main(["--config", "agent.yaml"]) == 2
    assert "install Debian's python3-rospy" in capsys.readouterr().err
