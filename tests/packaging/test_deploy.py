"""What runs the agent and the portal as services: the systemd units in deploy/systemd/ pass
`systemd-analyze verify` (no warning either), keep what must survive and stay private where
it belongs, and start the programs the packages install; the ROS 1 launch file gives the node
settings the agent accepts; the ROS 2 launch description runs the agent's command.
"""

import importlib.util
import os
import re
import shutil
import subprocess
import sys
import tomllib
import types
from pathlib import Path

import pytest
import yaml

from ros_agent import pairing
from ros_agent.config import config_from_mapping
from smcrypto import sm4
from tests.ros_agent.conftest import write_paired_robot_files
from tests.support.fresh_python import fresh_python
from tests.support.harness import REPO_ROOT

SYSTEMD = REPO_ROOT / "deploy" / "systemd"
UNITS = sorted(SYSTEMD.glob("*.service"))
PORTAL_UNITS = [
    "authros-beat.service",
    "authros-verify.service",
    "authros-web.service",
    "authros-worker.service",
]
ROS1_PACKAGE = REPO_ROOT / "deploy" / "ros1" / "authros_agent"
ROS2_LAUNCH = REPO_ROOT / "deploy" / "ros2" / "authros_agent" / "launch" / "authros_agent.launch.py"
AGENT_PREFIX, PORTAL_CHECKOUT = "/opt/authros-agent", "/srv/authros"
STATE_DIR = "/var/lib/authros-agent"


def unit_settings(path: Path) -> dict[str, list[str]]:
    """Each setting of a unit file (continued lines joined) and its values, in order."""
    found: dict[str, list[str]] = {}
    logical = ""
    for line in path.read_text().splitlines():
        if line.startswith(("#", ";", "[")) or not line.strip():
            continue
        logical += line.strip()
        if logical.endswith("\\"):
            logical = logical[:-1] + " "
            continue
        key, _, value = logical.partition("=")
        found.setdefault(key.strip(), []).append(value.strip())
        logical = ""
    return found


def project_scripts() -> dict[str, str]:
    return tomllib.loads((REPO_ROOT / "pyproject.toml").read_text())["project"]["scripts"]


def test_the_units_are_those_the_docs_install():
    assert [unit.name for unit in UNITS] == ["authros-agent.service", *PORTAL_UNITS]
    deployment = (REPO_ROOT / "docs" / "deployment.md").read_text()
    for unit in UNITS:
        assert unit.name in deployment


@pytest.mark.process
def test_each_unit_passes_systemd_analyze_verify_without_a_warning(tmp_path):
    analyze = shutil.which("systemd-analyze")
    assert analyze, "systemd-analyze is missing: scripts/bootstrap.sh installs Debian's systemd"
    # systemd checks that each program exists: the checkout is this one (its .venv), the
    # agent's prefix a folder with the console script pip writes for authros-agent.
    agent_bin = tmp_path / "agent" / "bin"
    agent_bin.mkdir(parents=True)
    module, function = project_scripts()["authros-agent"].split(":")
    script = agent_bin / "authros-agent"
    script.write_text(
        f"#!{sys.executable}\nimport sys\nfrom {module} import {function}\nsys.exit({function}())\n"
    )
    script.chmod(0o755)
    for unit in UNITS:
        text = unit.read_text()
        text = text.replace(AGENT_PREFIX, str(agent_bin.parent))
        text = text.replace(PORTAL_CHECKOUT, str(REPO_ROOT))
        copy = tmp_path / unit.name
        copy.write_text(text)
        checked = subprocess.run(
            [analyze, "verify", "--man=no", str(copy)],
            capture_output=True,
            text=True,
            timeout=60,
            check=False,
        )
        assert (checked.returncode, checked.stderr) == (0, ""), unit.name


@pytest.mark.process
def test_a_broken_unit_is_not_verified_quietly(tmp_path):
    """The check above sees a misspelt setting (a warning) and a missing program (an error)."""
    analyze = shutil.which("systemd-analyze")
    assert analyze
    broken = tmp_path / "broken.service"
    broken.write_text("[Service]\nExecStart=/nonexistent/bin/x\nProtectSystm=strict\n")
    checked = subprocess.run(
        [analyze, "verify", "--man=no", str(broken)],
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )
    assert checked.returncode != 0
    assert "Unknown key 'ProtectSystm'" in checked.stderr


def test_the_agent_unit_keeps_its_spool_and_secrets_private_and_restarts():
    unit = unit_settings(SYSTEMD / "authros-agent.service")
    assert unit["User"] == unit["Group"] == ["authros-agent"]
    # The spool and the paired files: /var/lib/authros-agent, 0700, files written 0600.
    assert unit["StateDirectory"] == ["authros-agent"]
    assert unit["StateDirectoryMode"] == ["0700"]
    assert unit["UMask"] == ["0077"]
    (command,) = unit["ExecStart"]
    program, *arguments = command.split()
    assert program == f"{AGENT_PREFIX}/bin/authros-agent"
    assert program.rsplit("/", 1)[1] in project_scripts()
    assert arguments[-2:] == ["--config", f"{STATE_DIR}/{pairing.CONFIG_FILE}"]
    assert unit["Restart"] == ["on-failure"]
    assert unit["RestartPreventExitStatus"] == ["2"]  # a refused setting: a restart won't mend it
    assert unit["KillSignal"] == ["SIGINT"]  # both agents send what they can on SIGINT
    for hardening in ("NoNewPrivileges", "ProtectHome", "PrivateTmp", "RestrictSUIDSGID"):
        assert unit[hardening] == ["yes"], hardening
    assert unit["ProtectSystem"] == ["strict"]  # writable: the state directory alone
    assert unit["CapabilityBoundingSet"] == [""]
    sysusers = (SYSTEMD / "authros-agent.sysusers.conf").read_text()
    assert f'u authros-agent - "AuthROS agent" {STATE_DIR}' in sysusers


@pytest.mark.process
def test_the_portal_units_run_the_checkouts_programs_with_their_settings_private():
    for name in PORTAL_UNITS:
        unit = unit_settings(SYSTEMD / name)
        assert unit["User"] == ["authros"], name
        assert unit["WorkingDirectory"] == [PORTAL_CHECKOUT], name
        assert unit["EnvironmentFile"] == ["/etc/authros/portal.env"], name
        assert unit["StateDirectoryMode"] == ["0700"], name
        assert unit["UMask"] == ["0077"], name
        assert unit["NoNewPrivileges"] == ["yes"], name
        assert unit["ProtectSystem"] == ["strict"], name
        assert unit["Restart"] == ["on-failure"], name
        (command,) = unit["ExecStart"]
        assert command.startswith(f"{PORTAL_CHECKOUT}/.venv/bin/"), name
    web = unit_settings(SYSTEMD / "authros-web.service")["ExecStart"][0].split()
    assert web[0].endswith("/gunicorn")
    assert "portal.wsgi:application" in web
    verify = unit_settings(SYSTEMD / "authros-verify.service")["ExecStart"][0].split()
    # The queues of a server's settings by default (the suite names its own in the
    # environment): the main one, and the one views' integrity checks are routed to.
    main, checks = fresh_python(
        "import django; django.setup(); from django.conf import settings as s; "
        "q = s.CELERY_TASK_DEFAULT_QUEUE; print(q, q + s.CELERY_VERIFY_QUEUE_SUFFIX)",
        unset=["CELERY_QUEUE"],
    ).split()
    worker = unit_settings(SYSTEMD / "authros-worker.service")["ExecStart"][0].split()
    assert worker[worker.index("-Q") + 1] == main
    assert verify[verify.index("-Q") + 1] == checks
    assert "--without-heartbeat" not in worker + verify  # monitors see the workers alive


def test_the_worker_unit_serves_its_hosts_metrics_on_a_port_of_its_own():
    """A host of workers alone is scraped at the worker (portal/worker_metrics.py), which adds
    up the counts of every service folder beside its own."""
    unit = unit_settings(SYSTEMD / "authros-worker.service")
    environment = dict(pair.split("=", 1) for line in unit["Environment"] for pair in line.split())
    assert int(environment["WORKER_METRICS_PORT"]) > 0
    assert environment["PROMETHEUS_MULTIPROC_DIR"] == "/run/authros/metrics/worker"
    web = unit_settings(SYSTEMD / "authros-web.service")["Environment"]
    assert any("PROMETHEUS_MULTIPROC_DIR=/run/authros/metrics/web" in line for line in web)


@pytest.mark.process
def test_the_ros1_launch_file_gives_the_node_settings_the_agent_accepts(tmp_path):
    """roslaunch reads the launch file (the agent.yaml pairing wrote, loaded as the node's
    parameters, the files beside it named by absolute path), finds the node's program in the
    package, and the parameters it would set are a config the agent takes."""
    folder = tmp_path / "paired"
    folder.mkdir()
    write_paired_robot_files(folder, sm4.generate_key())
    (folder / pairing.TOKEN_FILE).write_text("robot-token\n")
    (folder / pairing.TOKEN_FILE).chmod(0o600)
    (folder / pairing.CONFIG_FILE).write_text(
        yaml.safe_dump(
            {  # the settings ros_agent.pairing writes
                "portal_url": "https://portal.example.org",
                "token_file": pairing.TOKEN_FILE,
                "robot": "7c9e6679-7425-40de-944b-e07fc1f90ae7",
                "owner": "alice",
                "sm2_key_file": pairing.SM2_KEY_FILE,
                "keys_file": pairing.KEYS_FILE,
                "topics": [{"name": "/robot/odom", "type": "nav_msgs/Odometry"}],
                "spool_dir": "spool",
            }
        )
    )
    env = {**os.environ, "ROS_PACKAGE_PATH": str(ROS1_PACKAGE.parent)}
    launch = ROS1_PACKAGE / "launch" / "agent.launch"

    def roslaunch(*arguments: str) -> str:
        done = subprocess.run(
            ["roslaunch", *arguments, str(launch), f"dir:={folder}"],
            capture_output=True,
            text=True,
            env=env,
            timeout=60,
            check=False,
        )
        assert done.returncode == 0, done.stderr
        return done.stdout

    dumped = yaml.safe_load(roslaunch("--dump-params"))
    params = {key.removeprefix("/authros_agent/"): value for key, value in dumped.items()}
    config = config_from_mapping(params, source="roslaunch", base_dir=tmp_path / "elsewhere")
    assert config.spool_dir == folder / "spool"
    assert config.sm2_key_file == folder / pairing.SM2_KEY_FILE
    assert config.keys_file == folder / pairing.KEYS_FILE
    assert config.token == "robot-token"
    node = roslaunch("--args", "authros_agent").split()
    assert node[1] == str(ROS1_PACKAGE / "authros_agent")
    assert '"${AUTHROS_AGENT:-authros-agent}"' in (ROS1_PACKAGE / "authros_agent").read_text()


def test_the_ros2_launch_description_runs_the_agents_ros2_command():
    """ROS 2's launch package is not installed here: the file is loaded with stand-ins that
    record what it builds, named as ROS 2's launch API names them."""

    class Recorded:
        def __init__(self, *args: object, **kwargs: object) -> None:
            self.args, self.kwargs = args, kwargs

    class LaunchConfiguration(Recorded):
        pass

    stand_ins = {
        "launch": {"LaunchDescription": type("LaunchDescription", (Recorded,), {})},
        "launch.actions": {
            "DeclareLaunchArgument": type("DeclareLaunchArgument", (Recorded,), {}),
            "ExecuteProcess": type("ExecuteProcess", (Recorded,), {}),
        },
        "launch.substitutions": {"LaunchConfiguration": LaunchConfiguration},
    }
    with pytest.MonkeyPatch.context() as patch:
        for name, members in stand_ins.items():
            module = types.ModuleType(name)
            module.__dict__.update(members)
            patch.setitem(sys.modules, name, module)
        spec = importlib.util.spec_from_file_location("authros_agent_launch", ROS2_LAUNCH)
        assert spec
        assert spec.loader
        launch_file = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(launch_file)
        description = launch_file.generate_launch_description()
    (entities,) = description.args
    declared = {e.args[0]: e.kwargs["default_value"] for e in entities[:-1]}
    assert declared == {"config": f"{STATE_DIR}/{pairing.CONFIG_FILE}", "agent": "authros-agent"}
    process = entities[-1]
    assert type(process).__name__ == "ExecuteProcess"
    cmd = process.kwargs["cmd"]
    assert [c.args[0] if isinstance(c, LaunchConfiguration) else c for c in cmd] == [
        "agent",
        "--ros2",
        "--config",
        "config",
    ]
    assert declared["agent"] in project_scripts()
    assert process.kwargs["respawn"] is True


@pytest.mark.process
@pytest.mark.parametrize("unit", UNITS, ids=lambda unit: unit.name)
def test_each_unit_is_exposed_at_most_2_0_by_systemd_analyze_security(unit):
    """The hardening (SystemCallFilter, ProtectProc, ProcSubset, RemoveIPC, ...) measured as
    `systemd-analyze security --offline` rates it: 3.2 before it, 1.4-1.5 with it."""
    analyze = shutil.which("systemd-analyze")
    assert analyze, "systemd-analyze is missing: scripts/bootstrap.sh --test installs it"
    done = subprocess.run(
        [analyze, "security", "--offline=yes", "--threshold=20", str(unit)],
        capture_output=True, text=True, timeout=60, check=False,
    )  # fmt: skip
    assert done.returncode == 0, done.stdout[-2000:] + done.stderr
    overall = re.search(r"Overall exposure level for \S+: (\d+\.\d)", done.stdout)
    assert overall, done.stdout[-2000:]
    assert float(overall.group(1)) <= 2.0, done.stdout


def test_the_nginx_example_terminates_tls_and_passes_the_client_to_the_web_unit():
    conf = (REPO_ROOT / "deploy" / "nginx" / "authros.conf").read_text()
    web = unit_settings(SYSTEMD / "authros-web.service")["ExecStart"][0]
    assert "--bind 127.0.0.1:8000" in web
    assert "server 127.0.0.1:8000;" in conf
    assert "listen 443 ssl;" in conf
    assert "return 301 https://$host$request_uri;" in conf
    # one address, the client's, which API_NUM_PROXIES=1 reads
    assert "proxy_set_header X-Forwarded-For $remote_addr;" in conf
    assert "proxy_set_header X-Forwarded-Proto $scheme;" in conf
    assert "API_NUM_PROXIES=1" in conf
