"""The console scripts (authros_commands): `--version` on each, and a command whose extra is
missing here says which locked set to install in one line and exits 2, instead of a
traceback. Missing modules are made so in this process (None in sys.modules), with the
project's modules that import them loaded again; the installed wheel's own environments are
tried in tests/packaging/test_wheel.py."""

import sys
import tomllib
from collections.abc import Iterator

import pytest

import authros_commands
from tests.support.harness import REPO_ROOT

pytestmark = pytest.mark.nodb

SCRIPTS = tomllib.loads((REPO_ROOT / "pyproject.toml").read_text())["project"]["scripts"]


@pytest.fixture
def modules_restored() -> Iterator[None]:
    """sys.modules as it was once the test ends (what it imported again is dropped)."""
    saved = dict(sys.modules)
    yield
    for name in set(sys.modules) - set(saved):
        del sys.modules[name]
    sys.modules.update(saved)


def without(monkeypatch, missing: str, *reloaded: str) -> None:
    """`missing` cannot be imported, and the project's modules `reloaded` start with import."""
    for name in [m for m in sys.modules if m.split(".")[0] in reloaded]:
        monkeypatch.delitem(sys.modules, name)
    monkeypatch.setitem(sys.modules, missing, None)


def run(monkeypatch, capsys, script: str, *arguments: str) -> tuple[int, str, str]:
    monkeypatch.setattr(sys, "argv", [script, *arguments])
    entry = getattr(authros_commands, SCRIPTS[script].split(":")[1])
    code = entry()
    out, err = capsys.readouterr()
    return code, out, err


def test_both_scripts_go_through_the_commands_module():
    assert SCRIPTS == {
        "authros-agent": "authros_commands:agent",
        "authros-verify": "authros_commands:verify",
    }


@pytest.mark.parametrize("script", ["authros-agent", "authros-verify"])
def test_each_script_says_its_version(script, monkeypatch, capsys):
    monkeypatch.setattr(authros_commands, "version", lambda: "9.8.7")
    assert run(monkeypatch, capsys, script, "--version") == (0, f"{script} 9.8.7\n", "")


def test_the_version_is_the_installed_distributions_or_says_it_is_not_installed():
    version = authros_commands.version()
    assert version == "(not installed: run from a checkout)" or version[0].isdigit()


@pytest.mark.usefixtures("modules_restored")
@pytest.mark.parametrize(
    ("script", "arguments", "missing", "reloaded", "extra"),
    [
        ("authros-agent", ["pair", "--portal", "http://p", "--name", "r"], "yaml",
         ("ros_agent",), "agent"),
        ("authros-agent", ["--ros2", "--config", "agent.yaml"], "cyclonedds", (), "ros2"),
        ("authros-verify", ["proofs.json", "--rpc", "http://127.0.0.1:1"], "eth_utils",
         ("authros_verify", "web3"), "verify"),
    ],
)  # fmt: skip
def test_a_command_whose_extra_is_missing_says_what_to_install_and_exits_2(
    script, arguments, missing, reloaded, extra, monkeypatch, capsys
):
    without(monkeypatch, missing, *reloaded)
    code, out, err = run(monkeypatch, capsys, script, *arguments)
    assert code == 2
    assert out == ""
    assert err == (
        f"{script}: this environment lacks the [{extra}] extra (no module named {missing!r}): "
        f"install requirements/{extra}.txt into it (docs/deployment.md)\n"
    )


@pytest.mark.usefixtures("modules_restored")
def test_a_missing_module_of_the_project_itself_is_not_taken_for_a_missing_extra(monkeypatch):
    without(monkeypatch, "smcrypto", "ros_agent", "smcrypto")
    monkeypatch.setattr(sys, "argv", ["authros-agent", "pair", "--portal", "p", "--name", "r"])
    with pytest.raises(ModuleNotFoundError):
        authros_commands.agent()
