"""Fixtures for the agent: its owner's key, a paired robot's files and key, an in-test records
endpoint (one that requires the paired robot's signature too), the agent's yaml, a real ROS
master, a DDS domain of its own on this machine.

rospy allows one init_node per process, so every node under test (agent, simulator,
`rostopic pub`) runs in a subprocess against a `rosmaster --core` on a free port, with
ROS_HOME and ROS_LOG_DIR in the test's temporary folder. DDS stays on this machine: the
project's loopback-only CYCLONEDDS_URI, set before any participant exists, and a DDS domain
of this run's own.
"""

import contextlib
import json
import os
import re
import signal
import socket
import subprocess
import sys
import time
import xmlrpc.client
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

import genpy
import pytest
import yaml

from ros_agent import dds, sim
from ros_agent.extractors import extract
from ros_agent.keyring import key_id_hex, write_keys_file
from ros_agent.sealing import RobotSigningKey
from smcrypto import envelope, provenance, sm2, sm4
from stack.anvil import free_port
from tests.support.records_server import RecordsServer

REPO_ROOT = Path(__file__).resolve().parents[2]
OWNER = "alice"
ROBOT = "7c9e6679-7425-40de-944b-e07fc1f90ae7"
TOKEN = "robot-token-3f1c9a0d"
MASTER_STARTUP = 15.0
STOP_TIMEOUT = 10.0


@pytest.fixture
def owner_key() -> bytes:
    return sm4.generate_key()


@pytest.fixture
def key_file(tmp_path: Path, owner_key: bytes) -> Path:
    return write_key_file(tmp_path / "alice.sm4", owner_key)


@pytest.fixture
def portal(owner_key: bytes) -> Iterator[RecordsServer]:
    server = RecordsServer(token=TOKEN, key=owner_key, owner=OWNER, robot=ROBOT)
    server.start()
    yield server
    server.stop()


@pytest.fixture
def pairing_key(tmp_path: Path, owner_key: bytes) -> RobotSigningKey:
    """The robot's pairing key pair, its files written in tmp_path as pairing leaves them."""
    return RobotSigningKey.of(write_paired_robot_files(tmp_path, owner_key))


@pytest.fixture
def signing_portal(owner_key: bytes, pairing_key: RobotSigningKey) -> Iterator[RecordsServer]:
    """The records endpoint of a paired robot: every envelope must carry its signature."""
    server = RecordsServer(
        token=TOKEN,
        key=owner_key,
        owner=OWNER,
        robot=ROBOT,
        robot_public_key=pairing_key.public_key,
    )
    server.start()
    yield server
    server.stop()


def agent_yaml(
    folder: Path, portal: RecordsServer, topics: list[tuple[str, str]], *, paired: bool, **extra
) -> Path:
    """agent.yaml in `folder` for the in-test `portal`: a paired robot's (the files of
    `pairing_key`) or one set up by hand (`alice.sm4`); its spool in `folder/spool`."""
    keys = (
        {"sm2_key_file": "robot.sm2", "keys_file": "owner-keys.json"}
        if paired
        else {"key_file": "alice.sm4"}
    )
    settings = {
        "portal_url": portal.url,
        "token": TOKEN,
        "robot": ROBOT,
        "owner": OWNER,
        "topics": [{"name": name, "type": ros_type} for name, ros_type in topics],
        "spool_dir": "spool",
        **keys,
        **extra,
    }
    path = folder / "agent.yaml"
    path.write_text(yaml.safe_dump(settings))
    return path


def assert_batch_signed(
    portal: RecordsServer, key: RobotSigningKey, *, at_least: int = 1
) -> dict[str, list[int]]:
    """Every record `portal` stored is signed in a batch (provenance v2) by `key` and verifies
    on its own; every upload it took carries one batch signature; per topic, in the order
    stored, topic_seq counts 0, 1, 2, ... without a gap or a repeat. Returns the topic_seqs
    per topic."""
    assert len(portal.records) >= at_least
    by_seq = {}
    for stored in portal.records:
        info = envelope.read_header(stored.envelope)
        assert info.provenance == "v2", info.header
        assert info.signer == provenance.key_hash(key.public_key)
        header, plaintext = envelope.open(portal.key, stored.envelope)
        provenance.signature_check(key.public_key, header, plaintext)
        by_seq[stored.seq] = header
    for upload in portal.uploads:
        if upload.status == 201:
            assert len({by_seq[seq]["sig"] for seq in upload.seqs}) == 1, upload
    streams: dict[str, list[int]] = {}
    for stored in portal.records:
        streams.setdefault(stored.header["topic"], []).append(stored.header["topic_seq"])
    for topic, numbers in streams.items():
        assert numbers == list(range(len(numbers))), (topic, numbers)
    return streams


def write_key_file(path: Path, key: bytes, mode: int = 0o600) -> Path:
    path.write_text(key.hex() + "\n")
    path.chmod(mode)
    return path


def write_paired_robot_files(folder: Path, owner_key: bytes, *, mode: int = 0o600) -> str:
    """What pairing leaves on a robot: `robot.sm2` (its SM2 private key, returned) and
    `owner-keys.json` (the owner's key; `mode` for the file-mode checks)."""
    private_key, _public = sm2.generate_keypair()
    (folder / "robot.sm2").write_text(private_key + "\n")
    (folder / "robot.sm2").chmod(0o600)
    write_keys_file(
        folder / "owner-keys.json", {key_id_hex(owner_key): owner_key}, key_id_hex(owner_key)
    )
    (folder / "owner-keys.json").chmod(mode)
    return private_key


def chatter_record(text: str, time: str) -> dict:
    """The Fig. 4 record the agent makes of a std_msgs/String `text` on /chatter."""
    return {
        "K": {"data": text},
        "Owner": OWNER,
        "Time": time,
        "Type": "std_msgs/String",
        "Topic": "/chatter",
    }


def published_odometry(sim_log: Path) -> Callable[[dict], dict]:
    """What the simulator whose log is `sim_log` published at a stored odometry record's
    stamp, as the agent extracts it: the trajectory is a function of the time since the start
    stamp the simulator logs."""
    text = sim_log.read_text()
    match = re.search(re.escape(sim.START_MARK) + r"(\d+)\.(\d{9})", text)
    assert match, f"no start stamp in the simulator's log:\n{text[-2000:]}"
    start = genpy.Time(int(match[1]), int(match[2]))

    def at(stored: dict) -> dict:
        stamp = stored["header"]["stamp"]
        now = genpy.Time(stamp["secs"], stamp["nsecs"])
        msg = sim.odometry_message(sim.figure_eight((now - start).to_sec()), now)
        msg.header.seq = stored["header"]["seq"]  # rospy numbers messages as it sends them
        return json.loads(json.dumps(extract(msg, "nav_msgs/Odometry")))

    return at


def wait_until(
    condition: Callable[[], object], timeout: float, what: str, *, logs: Sequence[Path] = ()
) -> None:
    """Wait for `condition`; on a timeout, the failure shows the end of each of `logs` (what
    the processes under test said meanwhile)."""
    deadline = time.monotonic() + timeout
    while not condition():
        if time.monotonic() > deadline:
            tails = "".join(
                f"\n--- the end of {log} ---\n{log.read_text(errors='replace')[-4000:]}"
                for log in logs
                if log.exists()
            )
            raise AssertionError(f"timed out after {timeout} s waiting for {what}{tails}")
        time.sleep(0.05)


@dataclass(frozen=True)
class RosMaster:
    uri: str
    env: dict[str, str]
    home: Path


@pytest.fixture(scope="module")
def ros_master(tmp_path_factory: pytest.TempPathFactory) -> Iterator[RosMaster]:
    home = tmp_path_factory.mktemp("ros_home")
    port = free_port()
    uri = f"http://127.0.0.1:{port}/"
    env = {
        **os.environ,
        "ROS_MASTER_URI": uri,
        "ROS_HOME": str(home),
        "ROS_LOG_DIR": str(home / "log"),
        "ROS_IP": "127.0.0.1",
        "PYTHONUNBUFFERED": "1",
    }
    env.pop("ROS_HOSTNAME", None)
    env.pop("ROS_NAMESPACE", None)
    with running(
        ["rosmaster", "--core", "-p", str(port)], env=env, log=home / "master.log"
    ) as master:
        deadline = time.monotonic() + MASTER_STARTUP
        while not _master_answers(uri):
            if master.poll() is not None or time.monotonic() > deadline:
                log = (home / "master.log").read_text()
                pytest.fail(f"rosmaster did not come up on port {port}:\n{log}")
            time.sleep(0.1)
        yield RosMaster(uri=uri, env=env, home=home)


@contextlib.contextmanager
def running(
    command: list[str], *, env: dict[str, str], log: Path, stop_signal: int = signal.SIGINT
) -> Iterator[subprocess.Popen]:
    """Run a command for the duration of the block; stop it (then kill it) on the way out."""
    with log.open("wb") as output:
        process = subprocess.Popen(
            command, env=env, cwd=REPO_ROOT, stdout=output, stderr=subprocess.STDOUT
        )
        try:
            yield process
        finally:
            stop_process(process, stop_signal)


def stop_process(process: subprocess.Popen, stop_signal: int = signal.SIGINT) -> int:
    if process.poll() is None:
        process.send_signal(stop_signal)
        try:
            process.wait(STOP_TIMEOUT)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()
    return process.returncode


def python_module(module: str, *args: str) -> list[str]:
    return [sys.executable, "-m", module, *args]


def _master_answers(uri: str) -> bool:
    try:
        code, _, _ = xmlrpc.client.ServerProxy(uri).getSystemState("/pytest")
    except OSError:
        return False
    return code == 1


def _dds_domain_is_free(domain: int) -> bool:
    """No participant of another run on this machine holds the domain's first unicast port."""
    port = 7400 + 250 * domain + 10
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
        try:
            probe.bind(("127.0.0.1", port))
        except OSError:
            return False
    return True


_used_dds_domains: set[int] = set()


def free_dds_domain() -> int:
    """A DDS domain id (1..232) no other test of this run used and no other run holds."""
    start = os.getpid() % 200
    for offset in range(232):
        domain = 1 + (start + offset) % 232
        if domain not in _used_dds_domains and _dds_domain_is_free(domain):
            _used_dds_domains.add(domain)
            return domain
    raise AssertionError("no free DDS domain on this machine")


@pytest.fixture(scope="module")
def loopback_dds(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Path]:
    """The project's loopback-only Cyclone DDS config, in this process's environment before
    any participant is made (Cyclone reads it when the first one is)."""
    path = dds.write_loopback_config(tmp_path_factory.mktemp("dds") / "cyclonedds.xml")
    previous = os.environ.get(dds.CYCLONEDDS_URI)
    os.environ.update(dds.loopback_environment(path))
    yield path
    if previous is None:
        os.environ.pop(dds.CYCLONEDDS_URI, None)
    else:
        os.environ[dds.CYCLONEDDS_URI] = previous


@pytest.fixture
def ros2_env(loopback_dds: Path) -> tuple[int, dict[str, str]]:
    """A free DDS domain and the environment of processes that use it on loopback only."""
    domain = free_dds_domain()
    env = {**os.environ, **dds.loopback_environment(loopback_dds, domain_id=domain)}
    env["PYTHONUNBUFFERED"] = "1"
    return domain, env
