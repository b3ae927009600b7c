"""The agent's settings: `agent.yaml` (`--config`), or the node's private ROS parameters.

Both sources are one flat mapping with the same names and go through the same checks:

    portal_url: https://portal.example.org    # http(s); /api/v1/records/ is appended
    token: 3f1c...                            # the robot's token (robot_create prints it),
                                              # or token_file: a file holding it, mode 0600
    robot: 7c9e6679-7425-40de-944b-e07fc1f90ae7
    owner: alice
    key_file: alice.sm4                       # 32 hex digits, mode 0600; relative to the yaml
    # or, for a robot paired with `python -m ros_agent pair` (which writes all of this):
    # sm2_key_file: robot.sm2                 # the robot's SM2 private key, mode 0600
    # keys_file: owner-keys.json              # the owner's keys it was sent, mode 0600
    topics:
      - {name: /robot/odom, type: nav_msgs/Odometry}
    # optional, with their defaults:
    batch_size: 50                            # envelopes per upload at most
    batch_max_bytes: 1048576                  # envelope bytes per upload at most
    flush_interval: 1.0                       # seconds an envelope may wait for a full batch
    spool_dir: $ROS_HOME/authros_agent/<robot>
    spool_max_bytes: 268435456                # queue plus rejected/, on disk
    tls_verify: true                          # or false, or a CA bundle path
    request_timeout: 10.0
    backoff_max: 30.0                         # longest wait between retries, seconds
    stats_interval: 60.0                      # seconds between counter log lines
    shutdown_flush: 5.0                       # seconds spent sending at shutdown
    # ROS 2 (--ros2, and the import of recordings):
    ros2_distro: humble                       # or jazzy: the type store messages are read with
    msg_dirs: [msgs]                          # folders of <package>/msg/<Name>.msg: custom types
                                              # (then $AMENT_PREFIX_PATH/*/share is searched)

Relative paths are taken from the yaml's folder, or from the working directory for ROS
parameters. Prefer token_file over token with ROS parameters: anyone who can reach the ROS
master can read the parameter server.
"""

import os
import re
import stat
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

import yaml

from ros_agent.keyring import Keyring, KeyringError
from smcrypto import CryptoError, sm2, sm4

# The ROS 2 distributions whose interfaces the agent knows (rosbags' type stores).
ROS2_DISTROS = ("humble", "jazzy")
DEFAULT_ROS2_DISTRO = "humble"

_ROS_TYPE = re.compile(r"[A-Za-z][A-Za-z0-9_]*/[A-Za-z][A-Za-z0-9_]*")
_TOPIC_NAME = re.compile(r"~?/?[A-Za-z][A-Za-z0-9_]*(/[A-Za-z][A-Za-z0-9_]*)*")


class ConfigError(ValueError):
    """The settings are missing, malformed or unsafe; the message says which and how."""


@dataclass(frozen=True)
class TopicConfig:
    name: str
    type: str


@dataclass(frozen=True)
class AgentConfig:
    portal_url: str
    token: str = field(repr=False)
    robot: str
    owner: str
    key_file: Path | None
    key: bytes = field(repr=False)
    topics: tuple[TopicConfig, ...]
    spool_dir: Path
    batch_size: int = 50
    batch_max_bytes: int = 1024 * 1024
    flush_interval: float = 1.0
    spool_max_bytes: int = 256 * 1024 * 1024
    tls_verify: bool | str = True
    request_timeout: float = 10.0
    backoff_max: float = 30.0
    stats_interval: float = 60.0
    shutdown_flush: float = 5.0
    keys_file: Path | None = None
    sm2_key_file: Path | None = None
    sm2_private_key: str = field(default="", repr=False)
    keyring: Keyring | None = field(default=None, repr=False, compare=False)
    ros2_distro: str = DEFAULT_ROS2_DISTRO
    msg_dirs: tuple[Path, ...] = ()

    @property
    def records_url(self) -> str:
        return self.portal_url.rstrip("/") + "/api/v1/records/"

    @property
    def robot_key_url(self) -> str:
        return self.portal_url.rstrip("/") + "/api/v1/robot-key/"

    @property
    def msg_search_dirs(self) -> list[Path]:
        """Where custom ROS 2 message definitions are looked for: `msg_dirs`, then the share
        folders of the ROS 2 installs this process has sourced (AMENT_PREFIX_PATH)."""
        prefixes = os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep)
        return [*self.msg_dirs, *(Path(prefix) / "share" for prefix in prefixes if prefix)]

    @property
    def paired(self) -> bool:
        """Paired robots fetch a rotated key themselves; others have a key file set by hand."""
        return self.sm2_key_file is not None


# name -> (type check, lowest allowed value) for the optional numeric settings
_NUMBERS: dict[str, tuple[type, float]] = {
    "batch_size": (int, 1),
    "batch_max_bytes": (int, 1),
    "flush_interval": (float, 0.01),
    "spool_max_bytes": (int, 1),
    "request_timeout": (float, 0.1),
    "backoff_max": (float, 0.1),
    "stats_interval": (float, 0.1),
    "shutdown_flush": (float, 0.0),
}
_REQUIRED = ("portal_url", "robot", "owner", "topics")
_KEY_SETTINGS = ("key_file", "keys_file", "sm2_key_file")
_KNOWN = {
    *_REQUIRED,
    *_NUMBERS,
    *_KEY_SETTINGS,
    "token",
    "token_file",
    "spool_dir",
    "tls_verify",
    "ros2_distro",
    "msg_dirs",
}


def load_config(path: str | os.PathLike[str]) -> AgentConfig:
    """Read and check an agent.yaml; relative paths in it are taken from its folder."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise ConfigError(f"cannot read the config file {path}: {exc.strerror}") from None
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise ConfigError(f"{path} is not valid YAML: {exc}") from None
    return config_from_mapping(data, source=str(path), base_dir=path.parent)


def config_from_ros_params() -> AgentConfig:
    """Read and check the node's private parameters (~portal_url, ~token, ... ~topics)."""
    import rospy  # only here: the YAML path must work where rospy is not importable

    params = rospy.get_param("~", {})
    return config_from_mapping(params, source="ROS parameters (~)", base_dir=Path.cwd())


def config_from_mapping(data: Any, *, source: str, base_dir: Path) -> AgentConfig:
    """Check a settings mapping and build the config; errors name `source` and the setting."""
    if not isinstance(data, Mapping):
        raise ConfigError(f"{source}: expected a mapping of settings, got {type(data).__name__}")
    unknown = sorted(str(name) for name in data if name not in _KNOWN)
    if unknown:
        raise ConfigError(
            f"{source}: unknown setting(s) {', '.join(unknown)}; known: {', '.join(sorted(_KNOWN))}"
        )
    missing = [name for name in _REQUIRED if data.get(name) in (None, "", [])]
    if ("token" in data) == ("token_file" in data):
        missing.append("token (or token_file, not both)")
    paired = "keys_file" in data or "sm2_key_file" in data
    if ("key_file" in data) == paired or (
        paired and not {"keys_file", "sm2_key_file"} <= set(data)
    ):
        missing.append("key_file (or, for a paired robot, keys_file and sm2_key_file)")
    if missing:
        raise ConfigError(f"{source}: missing required setting(s): {', '.join(missing)}")

    def text(name: str) -> str:
        value = data[name]
        if not isinstance(value, str) or not value.strip():
            raise ConfigError(
                f"{source}: {name} must be a non-empty string (quote it if it looks like a number)"
            )
        return value.strip()

    portal_url = check_portal_url(text("portal_url"), source)
    robot = text("robot")
    key_file = _resolve(text("key_file"), base_dir) if "key_file" in data else None
    keys_file = sm2_key_file = None
    sm2_private_key = ""
    if key_file is not None:
        keyring = Keyring.of_one(read_key_file(key_file))
    else:
        keys_file = _resolve(text("keys_file"), base_dir)
        sm2_key_file = _resolve(text("sm2_key_file"), base_dir)
        sm2_private_key = read_sm2_key_file(sm2_key_file)
        try:
            keyring = Keyring.load(keys_file)
        except KeyringError as exc:
            raise ConfigError(str(exc)) from None
    numbers = {name: _number(data, name, source) for name in _NUMBERS if name in data}
    spool_dir = (
        _resolve(text("spool_dir"), base_dir) if "spool_dir" in data else _default_spool(robot)
    )
    return AgentConfig(
        portal_url=portal_url,
        token=text("token") if "token" in data else _token_file(text("token_file"), base_dir),
        robot=robot,
        owner=text("owner"),
        key_file=key_file,
        key=keyring.current()[1],
        topics=parse_topics(data["topics"], source),
        spool_dir=spool_dir,
        tls_verify=_tls_verify(data.get("tls_verify", True), base_dir, source),
        keys_file=keys_file,
        sm2_key_file=sm2_key_file,
        sm2_private_key=sm2_private_key,
        keyring=keyring,
        ros2_distro=_ros2_distro(data.get("ros2_distro", DEFAULT_ROS2_DISTRO), source),
        msg_dirs=_msg_dirs(data.get("msg_dirs", []), base_dir, source),
        **numbers,
    )


def read_key_file(path: Path) -> bytes:
    """The owner's SM4 key from a file of 32 hex digits that only its owner may read."""
    text = _read_private_file(path, "key file")
    try:
        key = bytes.fromhex(text)
    except ValueError:
        key = b""
    if len(key) != sm4.KEY_SIZE:
        raise ConfigError(
            f"the key file {path} must hold the SM4 key as {2 * sm4.KEY_SIZE} hex digits"
        )
    return key


def read_sm2_key_file(path: Path) -> str:
    """The robot's SM2 private key (64 hex digits) from a file only its owner may read."""
    text = _read_private_file(path, "SM2 key file").lower()
    try:
        sm2.public_key_from_private(text)
    except CryptoError:
        raise ConfigError(
            f"the SM2 key file {path} must hold the robot's SM2 private key as 64 hex digits"
        ) from None
    return text


def _read_private_file(path: Path, what: str) -> str:
    """The stripped text of a secret file, refused unless only its owner may read it."""
    try:
        mode = path.stat().st_mode
    except OSError as exc:
        raise ConfigError(f"cannot read the {what} {path}: {exc.strerror}") from None
    if not stat.S_ISREG(mode):
        raise ConfigError(f"the {what} {path} is not a regular file")
    if mode & 0o077:
        raise ConfigError(
            f"the {what} {path} has mode {stat.S_IMODE(mode):04o}, so other users may read "
            f"it; run: chmod 600 {path}"
        )
    try:
        return path.read_text(encoding="ascii").strip()
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(f"cannot read the {what} {path} as ASCII text: {exc}") from None


def _token_file(value: str, base_dir: Path) -> str:
    path = _resolve(value, base_dir)
    token = _read_private_file(path, "token file")
    if not token:
        raise ConfigError(f"the token file {path} is empty")
    return token


def check_portal_url(url: str, source: str) -> str:
    parts = urlsplit(url)
    if parts.scheme not in ("http", "https") or not parts.hostname:
        raise ConfigError(f"{source}: portal_url must be an http(s) URL, got {url!r}")
    if parts.query or parts.fragment:
        raise ConfigError(f"{source}: portal_url must not have a query or fragment: {url!r}")
    return url.rstrip("/")


def parse_topics(value: Any, source: str) -> tuple[TopicConfig, ...]:
    if not isinstance(value, list):
        raise ConfigError(f"{source}: topics must be a list of {{name, type}} entries")
    topics = []
    for index, entry in enumerate(value):
        where = f"{source}: topics[{index}]"
        if not isinstance(entry, Mapping) or set(entry) != {"name", "type"}:
            raise ConfigError(f"{where} must have exactly the keys name and type, got {entry!r}")
        name, ros_type = entry["name"], entry["type"]
        if not isinstance(name, str) or not _TOPIC_NAME.fullmatch(name):
            raise ConfigError(f"{where}: {name!r} is not a valid ROS topic name")
        if not isinstance(ros_type, str) or not _ROS_TYPE.fullmatch(ros_type):
            raise ConfigError(
                f"{where}: type {ros_type!r} must be package/Message, e.g. nav_msgs/Odometry"
            )
        topics.append(TopicConfig(name=name, type=ros_type))
    names = [topic.name for topic in topics]
    duplicates = sorted({name for name in names if names.count(name) > 1})
    if duplicates:
        raise ConfigError(f"{source}: topics listed twice: {', '.join(duplicates)}")
    return tuple(topics)


def _number(data: Mapping[str, Any], name: str, source: str) -> int | float:
    kind, lowest = _NUMBERS[name]
    value = data[name]
    allowed = (int,) if kind is int else (int, float)
    if isinstance(value, bool) or not isinstance(value, allowed):
        noun = "an integer" if kind is int else "a number"
        raise ConfigError(f"{source}: {name} must be {noun}, got {value!r}")
    if not value >= lowest:
        raise ConfigError(f"{source}: {name} must be at least {lowest}, got {value!r}")
    return kind(value)


def _tls_verify(value: Any, base_dir: Path, source: str) -> bool | str:
    if isinstance(value, bool):
        return value
    if isinstance(value, str) and value.strip():
        bundle = _resolve(value.strip(), base_dir)
        if not bundle.exists():
            raise ConfigError(
                f"{source}: tls_verify names a CA bundle that does not exist: {bundle}"
            )
        return str(bundle)
    raise ConfigError(f"{source}: tls_verify must be true, false or a CA bundle path")


def _ros2_distro(value: Any, source: str) -> str:
    if value not in ROS2_DISTROS:
        raise ConfigError(
            f"{source}: ros2_distro must be one of {', '.join(ROS2_DISTROS)}, got {value!r}"
        )
    return value


def _msg_dirs(value: Any, base_dir: Path, source: str) -> tuple[Path, ...]:
    if not isinstance(value, list) or not all(isinstance(v, str) and v.strip() for v in value):
        raise ConfigError(f"{source}: msg_dirs must be a list of folders")
    folders = tuple(_resolve(v.strip(), base_dir) for v in value)
    for folder in folders:
        if not folder.is_dir():
            raise ConfigError(f"{source}: msg_dirs names a folder that does not exist: {folder}")
    return folders


def _resolve(value: str, base_dir: Path) -> Path:
    path = Path(os.path.expandvars(value)).expanduser()
    return path if path.is_absolute() else (base_dir / path).resolve()


def _default_spool(robot: str) -> Path:
    ros_home = Path(os.environ.get("ROS_HOME") or Path.home() / ".ros")
    return ros_home / "authros_agent" / re.sub(r"[^A-Za-z0-9_.-]", "_", robot)
