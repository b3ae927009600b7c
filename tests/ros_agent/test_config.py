"""agent.yaml and ROS-parameter settings: defaults, paths, and clear refusals."""

from pathlib import Path

import pytest
import yaml

from ros_agent.config import AgentConfig, ConfigError, TopicConfig, config_from_mapping, load_config
from tests.ros_agent.conftest import OWNER, ROBOT, TOKEN, write_key_file


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
