"""The robot's and the auditor's locked sets on the machines robots are: Linux x86_64 and
aarch64 (Jetson, Raspberry Pi), Python 3.11-3.13.

- requirements/ROLE-linux-MACHINE.txt are the universal sets (requirements/ROLE.txt) as pip
  reads them on that machine: the same packages at the same versions, with the same hashes.
- Each aarch64 set downloads from wheels alone (no source to build on a robot), for each
  Python, with its dependencies resolved against it: what `pip install -r` does on the robot.
  It reads the package index for each set; the files are kept in the machine's cache
  (tests/support/downloads.py), so a fresh clone downloads only what an earlier run did not.
"""

import hashlib
import re
import sys
from pathlib import Path

import pytest
from packaging.markers import Marker
from packaging.utils import canonicalize_name

from tests.packaging.test_wheel import run
from tests.support.downloads import DOWNLOADS
from tests.support.harness import REPO_ROOT

REQUIREMENTS = REPO_ROOT / "requirements"
WHEELHOUSE = DOWNLOADS / "wheelhouse-platforms"
ROLES = ("agent", "verify")
MACHINES = ("x86_64", "aarch64")
PYTHONS = ("3.11", "3.12", "3.13")
# pip's names for the wheels a manylinux_2_28 aarch64 machine (Debian 10+, Ubuntu 20.04+) takes
AARCH64_PLATFORMS = ("manylinux2014_aarch64", "manylinux_2_28_aarch64")
# a pinned requirement: name, version, marker, then its hashes on the lines below
_PIN = re.compile(
    r"^([A-Za-z0-9][A-Za-z0-9._-]*)==(\S+)(?: ; ([^\\\n]*))? \\\n((?:\s+--hash=\S+(?: \\)?\n)+)",
    re.MULTILINE,
)


def pins(path: Path) -> dict[str, tuple[str, str | None, frozenset[str]]]:
    """Each package of a locked set: its version, marker and hashes."""
    return {
        canonicalize_name(name): (
            version,
            marker or None,
            frozenset(re.findall(r"sha256:(\w+)", hashes)),
        )
        for name, version, marker, hashes in _PIN.findall(path.read_text())
    }


def on_machine(machine: str, python: str) -> dict[str, str]:
    """The environment markers of Linux on that machine with that Python."""
    return {
        "sys_platform": "linux",
        "platform_system": "Linux",
        "platform_machine": machine,
        "os_name": "posix",
        "platform_python_implementation": "CPython",
        "implementation_name": "cpython",
        "python_version": python,
        "python_full_version": f"{python}.0",
    }


@pytest.mark.parametrize("machine", MACHINES)
@pytest.mark.parametrize("role", ROLES)
def test_each_platforms_set_is_the_universal_set_as_that_machine_reads_it(role, machine):
    universal = pins(REQUIREMENTS / f"{role}.txt")
    platform = pins(REQUIREMENTS / f"{role}-linux-{machine}.txt")
    environment = on_machine(machine, "3.11")
    expected = {
        name: version
        for name, (version, marker, _) in universal.items()
        if marker is None or Marker(marker).evaluate(environment)
    }
    assert {name: version for name, (version, _, _) in platform.items()} == expected
    for name, (_, marker, hashes) in platform.items():
        assert marker is None, name
        assert hashes, name
        assert hashes <= universal[name][2], name  # no file the universal set lacks


@pytest.mark.parametrize("role", ROLES)
def test_the_sm2_backend_in_c_and_no_opencv_or_dds_on_either_machine(role):
    aarch64 = pins(REQUIREMENTS / f"{role}-linux-aarch64.txt")
    x86_64 = pins(REQUIREMENTS / f"{role}-linux-x86_64.txt")
    assert "gmssl-fast" in aarch64
    assert "tongsuopy" not in aarch64
    assert "tongsuopy" in x86_64
    assert "gmssl-fast" not in x86_64
    for packages in (aarch64, x86_64):
        assert "gmssl" in packages  # the fallback, and the point arithmetic smcrypto calls
        assert not {"opencv-python-headless", "cyclonedds", "django"} & set(packages)


def _keep_only_the_locks_files(wheelhouse: Path, locked: Path) -> None:
    """Remove what an earlier lock downloaded: every file whose hash the lock does not name."""
    hashes = set().union(*(hashes for _, _, hashes in pins(locked).values()))
    for path in wheelhouse.glob("*") if wheelhouse.is_dir() else ():
        if hashlib.sha256(path.read_bytes()).hexdigest() not in hashes:
            path.unlink()


@pytest.mark.process
@pytest.mark.slow
@pytest.mark.timeout(1200)
@pytest.mark.parametrize("python", PYTHONS)
@pytest.mark.parametrize("role", ROLES)
def test_each_role_downloads_for_aarch64_from_wheels_alone(role, python, tmp_path):
    locked = REQUIREMENTS / f"{role}-linux-aarch64.txt"
    wheelhouse = WHEELHOUSE / f"{role}-aarch64-{python}"
    download = [sys.executable, "-m", "pip", "download", "-q", "--only-binary=:all:"]
    download += [f"--platform={platform}" for platform in AARCH64_PLATFORMS]
    download += ["--python-version", python, "--require-hashes", "-r", str(locked)]
    _keep_only_the_locks_files(wheelhouse, locked)  # a cache of earlier runs, earlier locks
    run([*download, "-d", str(wheelhouse)], cwd=tmp_path)
    wheels = {
        canonicalize_name(path.name.split("-")[0]): path.name for path in wheelhouse.iterdir()
    }
    assert set(wheels) == set(pins(locked))  # every package, and nothing the set does not hold
    for name in wheels.values():
        assert name.endswith(".whl"), name
        tags = name.removesuffix(".whl").split("-")[-1]
        assert tags == "any" or "aarch64" in tags, name
