"""The agent's ROS packages as a robot's workspace takes them: deploy/ros1/authros_agent is a
catkin package that catkin_make builds and installs in a workspace of its own (its program and
launch file where roslaunch finds them), deploy/ros2/authros_agent an ament_python package whose
setup.py installs the launch file where `ros2 launch authros_agent ...` looks (the ament index
marker, share/authros_agent/launch)."""

import os
import shutil
import subprocess
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest

from tests.support.harness import REPO_ROOT

ROS1 = REPO_ROOT / "deploy" / "ros1" / "authros_agent"
ROS2 = REPO_ROOT / "deploy" / "ros2" / "authros_agent"
# the robot's own Python, which has catkin_pkg (Debian's python3-catkin-pkg)
SYSTEM_PYTHON = "/usr/bin/python3"


def manifest(package: Path) -> ET.Element:
    return ET.parse(package / "package.xml").getroot()  # noqa: S314 (the repository's own file)


def test_the_ros1_package_is_a_catkin_package_that_installs_its_node_and_launch_file():
    root = manifest(ROS1)
    assert root.findtext("name") == "authros_agent"
    assert root.findtext("buildtool_depend") == "catkin"
    assert root.findtext("license") == "Apache-2.0"
    cmake = (ROS1 / "CMakeLists.txt").read_text()
    assert "project(authros_agent)" in cmake
    assert "catkin_package()" in cmake
    assert "install(PROGRAMS authros_agent" in cmake
    assert "install(DIRECTORY launch" in cmake
    assert os.access(ROS1 / "authros_agent", os.X_OK)


def test_the_ros2_package_is_ament_python_and_installs_its_launch_file():
    root = manifest(ROS2)
    assert root.get("format") == "3"
    assert root.findtext("name") == "authros_agent"
    assert root.findtext("export/build_type") == "ament_python"
    assert root.findtext("license") == "Apache-2.0"
    assert (ROS2 / "resource" / "authros_agent").is_file()
    assert [p.name for p in (ROS2 / "launch").glob("*.launch.py")] == ["authros_agent.launch.py"]


@pytest.mark.process
@pytest.mark.skipif(shutil.which("catkin_make") is None, reason="catkin is not installed")
def test_catkin_make_builds_and_installs_the_ros1_package_in_a_workspace(tmp_path):
    workspace = tmp_path / "catkin_ws"
    shutil.copytree(ROS1, workspace / "src" / "authros_agent")
    env = {"PATH": "/usr/bin:/bin", "HOME": str(tmp_path), "LANG": "C.UTF-8"}
    done = subprocess.run(
        ["catkin_make", f"-DPYTHON_EXECUTABLE={SYSTEM_PYTHON}", "install"],
        cwd=workspace,
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
        check=False,
    )
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
    installed = workspace / "install"
    assert os.access(installed / "lib" / "authros_agent" / "authros_agent", os.X_OK)
    assert (installed / "share" / "authros_agent" / "launch" / "agent.launch").is_file()
    (tmp_path / "agent.yaml").write_text("portal_url: https://portal.example.org\n")
    found = subprocess.run(
        [
            "bash",
            "-c",
            f"source {installed}/setup.bash && rospack find authros_agent && "
            f"roslaunch --args authros_agent authros_agent agent.launch dir:={tmp_path}",
        ],
        env=env,
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )
    assert found.returncode == 0, found.stderr
    package, node = found.stdout.split("\n")[:2]
    assert package == str(installed / "share" / "authros_agent")
    assert node.split()[0] == str(installed / "lib" / "authros_agent" / "authros_agent")


@pytest.mark.process
def test_the_ros2_packages_setup_installs_what_ros2_launch_looks_for(tmp_path):
    """What colcon's ament_python build runs: setup.py install into the workspace's prefix."""
    source = tmp_path / "src" / "authros_agent"
    shutil.copytree(ROS2, source)
    prefix = tmp_path / "install" / "authros_agent"
    done = subprocess.run(
        [sys.executable, "setup.py", "-q", "install", f"--prefix={prefix}",
         f"--install-data={prefix}", "--single-version-externally-managed",
         f"--record={tmp_path / 'record'}"],
        cwd=source, capture_output=True, text=True, timeout=120, check=False,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    share = prefix / "share"
    assert (share / "ament_index" / "resource_index" / "packages" / "authros_agent").is_file()
    assert (share / "authros_agent" / "package.xml").is_file()
    launch = share / "authros_agent" / "launch" / "authros_agent.launch.py"
    assert launch.read_bytes() == (ROS2 / "launch" / "authros_agent.launch.py").read_bytes()
