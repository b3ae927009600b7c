"""agent.yaml and ROS-parameter settings: defaults, paths, and clear refusals."""

import re
from datetime import UTC, datetime
from pathlib import Path

import pytest
import yaml
from django.core.exceptions import ValidationError

from accounts.agent_config import (
    DEFAULT_TOPICS,
    TOKEN_FILENAME,
    InvalidTopics,
    Topic,
    agent_config_yaml,
    topics_as_list,
    topics_parse,
)
from accounts.models import validate_robot_topics
from ros_agent.config import (
    AgentConfig,
    ConfigError,
    TopicConfig,
    config_from_mapping,
    load_config,
    parse_topics,
)
from ros_agent.keyring import Keyring, key_id_hex
from smcrypto import sm4
from tests.ros_agent.conftest import (
    OWNER,
    ROBOT,
    TOKEN,
    write_key_file,
    write_paired_robot_files,
)


def _settings(**overrides) -> dict:
    settings = {
        "portal_url": "https://portal.example.org/",
        "token": TOKEN,
        "robot": ROBOT,
        "owner": OWNER,
        "key_file": "alice.sm4",
        "topics": [
            {"name": "/robot/odom", "type": "nav_msgs/Odometry"},
            {"name": "/robot/complicatedImage", "type": "sensor_msgs/Image"},
        ],
    }
    settings.update(overrides)
    return {name: value for name, value in settings.items() if value is not None}


def _write(folder: Path, settings: dict) -> Path:
    path = folder / "agent.yaml"
    path.write_text(yaml.safe_dump(settings))
    return path


def test_yaml_config_with_defaults_and_paths_relative_to_it(tmp_path, key_file, owner_key):
    config = load_config(_write(tmp_path, _settings(spool_dir="spool")))

    assert isinstance(config, AgentConfig)
    assert config.key == owner_key
    assert config.key_file == key_file
    assert config.records_url == "https://portal.example.org/api/v1/records/"
    assert config.topics == (
        TopicConfig("/robot/odom", "nav_msgs/Odometry"),
        TopicConfig("/robot/complicatedImage", "sensor_msgs/Image"),
    )
    assert config.spool_dir == tmp_path / "spool"
    assert (config.batch_size, config.flush_interval, config.tls_verify) == (50, 1.0, True)
    assert TOKEN not in repr(config)
    assert owner_key.hex() not in repr(config)


def test_optional_settings_are_checked_and_converted(tmp_path, key_file):
    bundle = tmp_path / "ca.pem"
    bundle.write_text("not checked here")
    config = config_from_mapping(
        _settings(batch_size=10, flush_interval=2, spool_max_bytes=1000, tls_verify="ca.pem"),
        source="test",
        base_dir=tmp_path,
    )
    assert config.flush_interval == 2.0
    assert isinstance(config.flush_interval, float)
    assert config.tls_verify == str(bundle)


def test_custom_message_folders_then_the_installed_share_folders(tmp_path, key_file, monkeypatch):
    (tmp_path / "msgs").mkdir()
    monkeypatch.setenv("AMENT_PREFIX_PATH", "/opt/ros/jazzy:/home/robot/ws/install/my_pkg")
    config = config_from_mapping(
        _settings(ros2_distro="jazzy", msg_dirs=["msgs"]), source="test", base_dir=tmp_path
    )
    assert config.ros2_distro == "jazzy"
    assert config.msg_search_dirs == [
        tmp_path / "msgs",
        Path("/opt/ros/jazzy/share"),
        Path("/home/robot/ws/install/my_pkg/share"),
    ]
    monkeypatch.delenv("AMENT_PREFIX_PATH")
    default = config_from_mapping(_settings(), source="test", base_dir=tmp_path)
    assert (default.ros2_distro, default.msg_search_dirs) == ("humble", [])


def test_default_spool_is_under_ros_home_per_robot(tmp_path, key_file, monkeypatch):
    monkeypatch.setenv("ROS_HOME", str(tmp_path / "ros"))
    config = config_from_mapping(_settings(), source="test", base_dir=tmp_path)
    assert config.spool_dir == tmp_path / "ros" / "authros_agent" / ROBOT


def test_token_can_come_from_a_private_file(tmp_path, key_file):
    token_file = tmp_path / "robot.token"
    token_file.write_text(TOKEN + "\n")
    token_file.chmod(0o600)
    config = config_from_mapping(
        _settings(token=None, token_file="robot.token"), source="test", base_dir=tmp_path
    )
    assert config.token == TOKEN

    token_file.chmod(0o644)
    with pytest.raises(ConfigError, match=r"token file .* has mode 0644"):
        config_from_mapping(
            _settings(token=None, token_file="robot.token"), source="test", base_dir=tmp_path
        )
    token_file.write_text("")
    token_file.chmod(0o600)
    with pytest.raises(ConfigError, match=r"token file .* is empty"):
        config_from_mapping(
            _settings(token=None, token_file="robot.token"), source="test", base_dir=tmp_path
        )


@pytest.mark.parametrize("mode", [0o644, 0o640, 0o604, 0o660])
def test_key_file_readable_by_others_is_refused(tmp_path, owner_key, mode):
    write_key_file(tmp_path / "alice.sm4", owner_key, mode)
    with pytest.raises(ConfigError, match=rf"mode {mode:04o}.*chmod 600"):
        config_from_mapping(_settings(), source="test", base_dir=tmp_path)


@pytest.mark.parametrize("content", ["", "abc", "zz" * 16, "00" * 17])
def test_key_file_must_hold_32_hex_digits(tmp_path, content):
    path = tmp_path / "alice.sm4"
    path.write_text(content)
    path.chmod(0o600)
    with pytest.raises(ConfigError, match="32 hex digits"):
        config_from_mapping(_settings(), source="test", base_dir=tmp_path)


def test_missing_key_file(tmp_path):
    with pytest.raises(ConfigError, match="cannot read the key file"):
        config_from_mapping(_settings(), source="test", base_dir=tmp_path)


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        ({"token": None, "owner": ""}, r"missing required setting.*owner, token \(or token_file"),
        ({"token_file": "robot.token"}, r"token \(or token_file, not both\)"),
        ({"batch_szie": 3}, "unknown setting.*batch_szie"),
        ({"portal_url": "ftp://portal"}, "portal_url must be an http"),
        ({"portal_url": "https://"}, "portal_url must be an http"),
        ({"topics": "/odom"}, "topics must be a list"),
        ({"topics": [{"name": "/odom"}]}, r"topics\[0\] must have exactly the keys"),
        ({"topics": [{"name": "odom here", "type": "std_msgs/String"}]}, "not a valid ROS topic"),
        ({"topics": [{"name": "/odom", "type": "Odometry"}]}, "must be package/Message"),
        (
            {"topics": [{"name": "/a", "type": "std_msgs/String"}] * 2},
            "topics listed twice: /a",
        ),
        ({"batch_size": 0}, "batch_size must be at least 1"),
        ({"batch_size": 2.5}, "batch_size must be an integer"),
        ({"flush_interval": "soon"}, "flush_interval must be a number"),
        ({"flush_interval": True}, "flush_interval must be a number"),
        ({"tls_verify": "missing.pem"}, "CA bundle that does not exist"),
        ({"robot": 42}, "robot must be a non-empty string"),
        ({"ros2_distro": "rolling"}, "ros2_distro must be one of humble, jazzy"),
        ({"msg_dirs": "msgs"}, "msg_dirs must be a list of folders"),
        ({"msg_dirs": ["missing"]}, "msg_dirs names a folder that does not exist"),
    ],
)
def test_bad_settings_are_refused_with_a_clear_message(tmp_path, key_file, overrides, message):
    with pytest.raises(ConfigError, match=message):
        config_from_mapping(_settings(**overrides), source="agent.yaml", base_dir=tmp_path)


def test_unreadable_or_non_mapping_yaml(tmp_path):
    with pytest.raises(ConfigError, match="cannot read the config file"):
        load_config(tmp_path / "absent.yaml")
    (tmp_path / "agent.yaml").write_text("- just\n- a list\n")
    with pytest.raises(ConfigError, match="expected a mapping"):
        load_config(tmp_path / "agent.yaml")
    (tmp_path / "agent.yaml").write_text("portal_url: [unclosed\n")
    with pytest.raises(ConfigError, match="not valid YAML"):
        load_config(tmp_path / "agent.yaml")


# --- the portal's side of the format (accounts/agent_config.py) -------------------------------
# The portal writes agent.yaml and checks the topics owners type in, without importing the
# agent: these tests hold the two sides to one format.


@pytest.mark.parametrize("token", [TOKEN, None])
def test_the_agent_loads_the_config_the_portal_writes(tmp_path, key_file, token):
    topics = (
        Topic("/robot/odom", "nav_msgs/Odometry"),
        Topic("~scan", "sensor_msgs/LaserScan"),
        Topic("front_camera/image_raw", "sensor_msgs/Image"),
    )
    text = agent_config_yaml(
        portal_url="https://portal.example.org/",
        robot_id=ROBOT,
        robot_name="turtle 1",
        owner_username=OWNER,
        topics=topics,
        token=token,
        made_at=datetime(2026, 3, 1, 12, 0, tzinfo=UTC),
    )
    config_file = tmp_path / "agent.yaml"
    config_file.write_text(text)
    # The file names the key file it expects; the owner puts it beside the config.
    assert yaml.safe_load(text)["key_file"] == key_file.name
    if token is None:
        token_file = tmp_path / TOKEN_FILENAME
        token_file.write_text(TOKEN)
        token_file.chmod(0o600)

    config = load_config(config_file)

    assert [(topic.name, topic.type) for topic in config.topics] == [
        (topic.name, topic.type) for topic in topics
    ]
    assert (config.robot, config.owner, config.token) == (ROBOT, OWNER, TOKEN)
    assert config.records_url == "https://portal.example.org/api/v1/records/"
    assert config.key_file == key_file


def test_the_agent_takes_the_optional_settings_the_portal_writes(tmp_path, owner_key):
    write_key_file(tmp_path / "sm4.key", owner_key)
    text = agent_config_yaml(
        portal_url="http://127.0.0.1:8000",
        robot_id=ROBOT,
        robot_name="demo",
        owner_username=OWNER,
        topics=DEFAULT_TOPICS,
        token=TOKEN,
        made_at=datetime(2026, 3, 1, tzinfo=UTC),
        key_file="sm4.key",
        options={"batch_size": 20, "flush_interval": 1.0, "spool_dir": "spool"},
    )
    config = load_config(_write_text(tmp_path, text))
    assert (config.batch_size, config.flush_interval) == (20, 1.0)
    assert config.spool_dir == tmp_path / "spool"
    assert config.key == owner_key


def _write_text(folder: Path, text: str) -> Path:
    path = folder / "agent.yaml"
    path.write_text(text)
    return path


def test_the_portals_default_topics_are_valid_for_the_agent():
    assert parse_topics(topics_as_list(DEFAULT_TOPICS), "topics") == tuple(
        TopicConfig(topic.name, topic.type) for topic in DEFAULT_TOPICS
    )


def _entry(name: object, ros_type: object = "std_msgs/String") -> dict:
    return {"name": name, "type": ros_type}


# Topic values run through both sides: None where both accept them, else a part of the
# message both give.
TOPIC_CASES = [
    ([_entry("/robot/odom", "nav_msgs/Odometry")], None),
    ([_entry("~odom"), _entry("~/private"), _entry("relative/name_2")], None),
    ([_entry("/a/b_c/d1", "my_pkg2/My_Msg_3")], None),
    ([], None),  # an empty list: each side has its own message, both refuse
    (None, None),
    ("", None),
    ("/odom std_msgs/String", "topics must be a list"),
    ({"name": "/odom", "type": "std_msgs/String"}, "topics must be a list"),
    ([["/odom", "std_msgs/String"]], "topics[0] must have exactly the keys name and type"),
    ([{"name": "/odom"}], "topics[0] must have exactly the keys name and type"),
    ([{**_entry("/odom"), "rate": 10}], "topics[0] must have exactly the keys name and type"),
    ([_entry("/ok"), _entry("odom here")], "topics[1]: 'odom here' is not a valid ROS topic"),
    ([_entry("/1odom")], "is not a valid ROS topic name"),
    ([_entry("//odom")], "is not a valid ROS topic name"),
    ([_entry("/odom/")], "is not a valid ROS topic name"),
    ([_entry("/odöm")], "is not a valid ROS topic name"),
    ([_entry("")], "is not a valid ROS topic name"),
    ([_entry(5)], "5 is not a valid ROS topic name"),
    ([_entry("/odom", "Odometry")], "type 'Odometry' must be package/Message"),
    ([_entry("/odom", "nav_msgs/Odometry/x")], "must be package/Message"),
    ([_entry("/odom", "nav_msgs/")], "must be package/Message"),
    ([_entry("/odom", None)], "type None must be package/Message"),
    ([_entry("/a"), _entry("/b"), _entry("/a")], "topics listed twice: /a"),
]
_VALID = {0, 1, 2}


def _agent_refusal(value: object, tmp_path: Path) -> str | None:
    """What the agent's loader says of these topics in an otherwise valid agent.yaml."""
    settings = _settings()
    settings["topics"] = value
    try:
        config_from_mapping(settings, source="agent.yaml", base_dir=tmp_path)
    except ConfigError as exc:
        return str(exc)
    return None


def _portal_refusal(value: object) -> str | None:
    """What the portal says of the same topics when a robot is added (its topic check)."""
    try:
        topics_parse(value)
    except InvalidTopics as exc:
        return str(exc)
    return None


def _model_refusal(value: object) -> str | None:
    """What the Robot model's validator says of them (the admin, a full_clean)."""
    try:
        validate_robot_topics(value)
    except ValidationError as exc:
        return " ".join(exc.messages)
    return None


@pytest.mark.parametrize(("index", "case"), list(enumerate(TOPIC_CASES)))
def test_the_portal_refuses_the_topics_the_agent_refuses(tmp_path, key_file, index, case):
    value, fragment = case
    agent, portal = _agent_refusal(value, tmp_path), _portal_refusal(value)
    assert _model_refusal(value) == portal
    assert (agent is None, portal is None) == (index in _VALID, index in _VALID)
    if fragment is not None:
        assert fragment in agent
        assert fragment in portal
        # The agent names its source first; after that, the two messages are the same.
        assert agent == f"agent.yaml: {portal}"


# --- a paired robot's settings (issue 14) --------------------------------------------------


def test_a_paired_robots_config_names_its_sm2_key_and_its_keys(tmp_path, owner_key):
    private_key = write_paired_robot_files(tmp_path, owner_key)
    settings = _settings(key_file=None, sm2_key_file="robot.sm2", keys_file="owner-keys.json")
    config = load_config(_write(tmp_path, settings))
    assert config.paired
    assert config.key_file is None
    assert config.key == owner_key
    assert config.sm2_private_key == private_key
    assert config.keyring.current() == (key_id_hex(owner_key), owner_key)
    assert config.robot_key_url == "https://portal.example.org/api/v1/robot-key/"
    assert private_key not in repr(config)


def test_a_new_key_is_kept_on_disk_beside_the_old_ones(tmp_path, owner_key):
    write_paired_robot_files(tmp_path, owner_key)
    keyring = Keyring.load(tmp_path / "owner-keys.json")
    new_key = sm4.generate_key()
    assert keyring.add(new_key) is True
    assert keyring.add(new_key) is False
    again = Keyring.load(tmp_path / "owner-keys.json")
    assert again.current() == (key_id_hex(new_key), new_key)
    assert again.get(key_id_hex(owner_key)) == owner_key
    assert (tmp_path / "owner-keys.json").stat().st_mode & 0o777 == 0o600


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        ({"sm2_key_file": "robot.sm2", "keys_file": "owner-keys.json"}, "key_file (or"),
        ({"key_file": None, "sm2_key_file": "robot.sm2"}, "key_file (or"),
        ({"key_file": None, "keys_file": "owner-keys.json"}, "key_file (or"),
        ({"key_file": None}, "key_file (or"),
    ],
)
def test_key_settings_are_one_key_file_or_a_pairing(tmp_path, owner_key, overrides, message):
    write_key_file(tmp_path / "alice.sm4", owner_key)
    write_paired_robot_files(tmp_path, owner_key)
    with pytest.raises(ConfigError, match=re.escape(message)):
        load_config(_write(tmp_path, _settings(**overrides)))


def test_a_keys_file_others_may_read_is_refused(tmp_path, owner_key):
    write_paired_robot_files(tmp_path, owner_key, mode=0o644)
    settings = _settings(key_file=None, sm2_key_file="robot.sm2", keys_file="owner-keys.json")
    with pytest.raises(ConfigError, match="chmod 600"):
        load_config(_write(tmp_path, settings))
