"""The wheel as a robot and an auditor install it: built from pyproject.toml, installed with
its role's locked set (requirements/ROLE.txt, hashes required) into a fresh virtual
environment each, and run from a folder outside the repository, which is on no path.

- the robot's (`[agent]`, with Debian's ROS 1 through --system-site-packages): each
  `authros-agent` command answers, the ROS 1 node loads rospy, Django is not there, and the
  systemd unit verifies against this very install;
- the auditor's (`[verify]`, nothing of the system's): `authros-verify` checks an export the
  portal made against the session's chain, and fails it once a byte of it changes.

The packages come from a wheelhouse per role in the machine's cache (tests/support/downloads.py),
filled with what it lacks (`pip download`), then offline.
"""

import json
import os
import shutil
import subprocess
import sys
import tomllib
import zipfile
from pathlib import Path

import pytest
from django.conf import settings

from tests.authros_verify.conftest import export_of
from tests.support.downloads import DOWNLOADS
from tests.support.harness import REPO_ROOT

pytestmark = [pytest.mark.process, pytest.mark.slow, pytest.mark.timeout(1200)]

WHEELHOUSE = DOWNLOADS / "wheelhouse"
PACKAGES = ("ros_agent", "authros_verify", "smcrypto")
MODULES = ("authros_commands.py",)  # the console scripts' entry points
# The interpreter the virtual environments are made from: the system's, as on a robot.
BASE_PYTHON = getattr(sys, "_base_executable", sys.executable)


def run(command: list[str], *, cwd: Path, check: bool = True) -> subprocess.CompletedProcess:
    """`command` from `cwd`, with no PYTHONPATH (the repository is on no path)."""
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "VIRTUAL_ENV")}
    done = subprocess.run(
        command, cwd=cwd, env=env, capture_output=True, text=True, timeout=900, check=False
    )
    if check:
        assert done.returncode == 0, f"{command}\n{done.stdout[-3000:]}\n{done.stderr[-3000:]}"
    return done


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> Path:
    """The wheel, built from a copy of what it is made of (setuptools leaves its build
    folders beside the sources)."""
    source = tmp_path_factory.mktemp("source")
    for name in ("pyproject.toml", "README.md", "LICENSE", *MODULES):
        shutil.copy(REPO_ROOT / name, source / name)
    for package in PACKAGES:
        shutil.copytree(
            REPO_ROOT / package, source / package, ignore=shutil.ignore_patterns("__pycache__")
        )
    dist = tmp_path_factory.mktemp("dist")
    run([sys.executable, "-m", "pip", "wheel", "--no-deps", "-q", "-w", str(dist), "."], cwd=source)
    (built,) = dist.glob("authros_portal-*.whl")
    return built


def role_venv(folder: Path, role: str, wheel: Path, *, system_site_packages: bool) -> Path:
    """A fresh virtual environment with the role's locked set and the wheel: its bin/."""
    locked = REPO_ROOT / "requirements" / f"{role}.txt"
    wheelhouse = WHEELHOUSE / role  # one per role: the two tests may run at once
    offline = ["--no-index", "--find-links", str(wheelhouse)]
    download = [sys.executable, "-m", "pip", "download", "-q", "--no-deps", "--require-hashes"]
    download += ["-r", str(locked), "-d", str(wheelhouse)]
    if run([*download, *offline], cwd=folder, check=False).returncode != 0:
        run(download, cwd=folder)  # once: what the wheelhouse lacks, from the index
    venv = folder / f"{role}-venv"
    run(
        [BASE_PYTHON, "-m", "venv", *(["--system-site-packages"] if system_site_packages else []),
         str(venv)],
        cwd=folder,
    )  # fmt: skip
    # No bytecode compiled at install (a third of pip's time here, numpy and OpenCV above
    # all): the commands below compile what they import, as a first run on a robot does.
    pip = [
        str(venv / "bin" / "python"),
        "-m",
        "pip",
        "install",
        "-q",
        "--disable-pip-version-check",
        "--no-compile",
    ]
    run([*pip, *offline, "--require-hashes", "-r", str(locked)], cwd=folder)
    # Offline and with no other index: the extra's packages must all be in the locked set.
    run([*pip, *offline, f"{wheel}[{role}]"], cwd=folder)
    return venv / "bin"


def test_the_wheel_holds_the_robots_and_the_auditors_packages_and_commands(wheel):
    with zipfile.ZipFile(wheel) as archive:
        names = archive.namelist()
        entry_points = archive.read(
            next(n for n in names if n.endswith(".dist-info/entry_points.txt"))
        ).decode()
        metadata = archive.read(next(n for n in names if n.endswith(".dist-info/METADATA")))
    top = {name.split("/")[0] for name in names if "dist-info" not in name}
    assert top == {*PACKAGES, *MODULES}
    assert "ros_agent/agent.example.yaml" in names
    assert "authros-agent = authros_commands:agent" in entry_points
    assert "authros-verify = authros_commands:verify" in entry_points
    assert b"\nLicense-Expression: Apache-2.0\n" in metadata
    assert any(name.endswith(".dist-info/licenses/LICENSE") for name in names)


def test_the_agent_installs_alone_and_each_command_answers(wheel, tmp_path):
    bin_dir = role_venv(tmp_path, "agent", wheel, system_site_packages=True)
    agent = str(bin_dir / "authros-agent")
    version = tomllib.loads((REPO_ROOT / "pyproject.toml").read_text())["project"]["version"]
    assert run([agent, "--version"], cwd=tmp_path).stdout == f"authros-agent {version}\n"
    # The auditor's command is there too, and says what it needs instead of a traceback.
    verify = run(
        [str(bin_dir / "authros-verify"), "p.json", "--rpc", "x"], cwd=tmp_path, check=False
    )
    assert verify.returncode == 2
    assert verify.stderr.startswith("authros-verify: this environment lacks the [verify] extra")
    assert len(verify.stderr.splitlines()) == 1
    overview = run([agent, "--help"], cwd=tmp_path).stdout
    assert "pair --portal URL --name NAME" in overview
    assert "--ros2 --config agent.yaml" in overview
    assert "usage:" in run([agent, "pair", "--help"], cwd=tmp_path).stdout
    assert "--portal PORTAL" in run([agent, "pair", "--help"], cwd=tmp_path).stdout
    assert "--domain-id" in run([agent, "--ros2", "--help"], cwd=tmp_path).stdout
    # A ROS 1 robot's set has no DDS: the ROS 2 agent says which set has it.
    ros2 = run([agent, "--ros2", "--config", "agent.yaml"], cwd=tmp_path, check=False)
    assert ros2.returncode == 2
    assert "lacks the [ros2] extra (no module named 'cyclonedds')" in ros2.stderr
    assert "--config" in run([agent, "import", "--help"], cwd=tmp_path).stdout
    # The ROS 1 node: rospy from Debian, seen through --system-site-packages.
    assert (
        "--config CONFIG" in run([agent, "--config", "agent.yaml", "--help"], cwd=tmp_path).stdout
    )
    loaded = run(
        [str(bin_dir / "python"), "-c",
         "import sys, json, ros_agent, ros_agent.pairing, ros_agent.ros2, ros_agent.bags, "
         "ros_agent.node\n"
         "print(json.dumps([ros_agent.__file__, sorted({m.split('.')[0] for m in sys.modules})]))"],
        cwd=tmp_path,
    )  # fmt: skip
    where, modules = json.loads(loaded.stdout)
    assert where.startswith(str(bin_dir.parent)), where  # the installed copy, not the checkout
    assert not {"django", "rest_framework", "celery", "portal", "accounts", "sharing"} & set(
        modules
    )
    no_django = run([str(bin_dir / "python"), "-c", "import django"], cwd=tmp_path, check=False)
    assert "No module named 'django'" in no_django.stderr
    # The unit verifies against this install (tests/packaging/test_deploy.py checks the rest).
    analyze = shutil.which("systemd-analyze")
    assert analyze, "systemd-analyze is missing: scripts/bootstrap.sh installs Debian's systemd"
    unit = tmp_path / "authros-agent.service"
    unit.write_text(
        (REPO_ROOT / "deploy/systemd/authros-agent.service")
        .read_text()
        .replace("/opt/authros-agent", str(bin_dir.parent))
    )
    checked = run([analyze, "verify", "--man=no", str(unit)], cwd=tmp_path, check=False)
    assert (checked.returncode, checked.stderr) == (0, "")


@pytest.mark.django_db
def test_the_verifier_installs_alone_and_checks_an_export_against_the_chain(
    wheel, tmp_path, make_paired_robot, django_capture_on_commit_callbacks, deployed
):
    setup = make_paired_robot("alice")  # its envelopes are signed
    envelopes = [
        setup.seal(
            seq,
            topic="/chatter",
            data_type="std_msgs/String",
            time=f"2026-05-01T12:00:0{seq}.000001Z",
            plaintext=json.dumps({"K": {"data": f"msg {seq}"}}).encode(),
        )
        for seq in (1, 2)
    ]
    bundle, mcap = export_of(setup, django_capture_on_commit_callbacks, envelopes)
    (tmp_path / "proofs.json").write_bytes(bundle)
    (tmp_path / "export.mcap").write_bytes(mcap)

    bin_dir = role_venv(tmp_path, "verify", wheel, system_site_packages=False)
    verify = str(bin_dir / "authros-verify")
    assert "--require-signed" in run([verify, "--help"], cwd=tmp_path).stdout
    assert run([verify, "--version"], cwd=tmp_path).stdout.startswith("authros-verify 0.")
    pair = [str(bin_dir / "authros-agent"), "pair", "--portal", "http://p", "--name", "r"]
    paired = run(pair, cwd=tmp_path, check=False)
    assert paired.returncode == 2
    assert paired.stderr == (
        "authros-agent: this environment lacks the [agent] extra (no module named 'yaml'): "
        "install requirements/agent.txt into it (docs/deployment.md)\n"
    )
    command = [verify, "proofs.json", "--mcap", "export.mcap", "--rpc", settings.CHAIN_RPC_URL]
    command += ["--contract", deployed.address, "--require-signed"]
    passed = run(command, cwd=tmp_path)
    assert "2 of 2 records verified against the chain: 2 genuine" in passed.stdout
    assert passed.stdout.strip().splitlines()[-1] == (
        f"VERIFIED: 2 records, 0 refused, chain {deployed.w3.eth.chain_id} "
        f"contract {deployed.address}"
    )
    # One changed byte of a message fails it, naming the record.
    (tmp_path / "export.mcap").write_bytes(mcap.replace(b"msg 2", b"msg 3"))
    failed = run(command, cwd=tmp_path, check=False)
    second = json.loads(bundle)["records"][1]["record"]
    assert failed.returncode == 1, failed.stdout + failed.stderr
    assert f"FAIL record {second}" in failed.stdout
    # Nothing of the portal, of Django, of ROS or of the agent's DDS is there.
    for module in ("django", "sharing", "rospy", "cyclonedds"):
        missing = run(
            [str(bin_dir / "python"), "-c", f"import {module}"], cwd=tmp_path, check=False
        )
        assert f"No module named '{module}'" in missing.stderr
