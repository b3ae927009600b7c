"""`manage.py owner_create` and `manage.py robot_create`: provisioning fleets without a browser."""

import json
import os
import subprocess
import sys
from io import StringIO
from pathlib import Path

import pytest
from django.core.management import CommandError, call_command

from accounts.keyexchange import portal_sm2_public_key
from accounts.models import ChainState, Owner, Robot
from accounts.selectors import owner_key_bytes, owner_key_current, robot_by_token
from smcrypto import key_id, sm2, sm4
from stack.anvil import start_anvil
from tests.support.robot_setup import TEST_PASSWORD

REPO_ROOT = Path(__file__).resolve().parents[2]
# A well-formed key that looks random, for tests about the other arguments.
SOME_KEY_HEX = "5f0c9e27b3a1d84e6c72f19a0b3d5e88"
pytestmark = pytest.mark.django_db


def _owner_create(*args: str, password: str = TEST_PASSWORD + "\n") -> dict:
    out = StringIO()
    call_command("owner_create", *args, stdin=StringIO(password), stdout=out, stderr=StringIO())
    return json.loads(out.getvalue())


def _robot_create(*args: str) -> dict:
    out = StringIO()
    call_command("robot_create", *args, stdout=out)
    return json.loads(out.getvalue())


def test_owner_create_registers_on_chain_and_prints_json(deployed):
    key = sm4.generate_key()
    result = _owner_create("--username", "alice", "--sm4-key-hex", key.hex().upper())
    owner = Owner.objects.get(user__username="alice")
    assert result == {
        "username": "alice",
        "eoa": owner.eoa_address,
        "address": owner.eoa_address,
        "key_id": key_id(key).hex(),
        "chain_state": "confirmed",
        "register_tx": owner.register_tx,
        "registered_block": owner.registered_block,
    }
    assert owner.chain_state == ChainState.CONFIRMED
    assert deployed.is_registered(owner.eoa_address)
    assert owner.user.check_password(TEST_PASSWORD)


def test_owner_create_reads_the_key_from_a_file(deployed, tmp_path):
    key = sm4.generate_key()
    key_file = tmp_path / "alice.sm4"
    key_file.write_text(key.hex() + "\n")
    key_file.chmod(0o644)
    with pytest.raises(CommandError, match="chmod 600"):
        _owner_create("--username", "alice", "--sm4-key-file", str(key_file))
    assert not Owner.objects.exists()
    key_file.chmod(0o600)
    result = _owner_create("--username", "alice", "--sm4-key-file", str(key_file))
    assert result["key_id"] == key_id(key).hex()


def test_owner_create_takes_the_key_sm2_encrypted_to_the_portal(deployed):
    key = sm4.generate_key()
    ciphertext = sm2.encrypt(portal_sm2_public_key(), key)
    result = _owner_create("--username", "alice", "--sm4-key-sm2", ciphertext)
    assert result["key_id"] == key_id(key).hex()
    assert "sm4_key_hex" not in result  # given, so not shown again
    assert owner_key_bytes(owner_key_current(Owner.objects.get())) == key


def test_owner_create_refuses_a_key_encrypted_to_another_portal(deployed):
    other_public = sm2.generate_keypair()[1]
    with pytest.raises(CommandError, match="could not be decrypted"):
        _owner_create(
            "--username", "alice", "--sm4-key-sm2", sm2.encrypt(other_public, sm4.generate_key())
        )
    assert not Owner.objects.exists()


@pytest.mark.parametrize(
    ("args", "password", "message"),
    [
        (["--sm4-key-hex", "abcd"], TEST_PASSWORD, "32 hex digits"),
        (["--sm4-key-hex", "zz" * 16], TEST_PASSWORD, "32 hex digits"),
        (["--sm4-key-hex", "00" * 16], TEST_PASSWORD, "all-zero"),
        (["--sm4-key-file", "/nonexistent/key"], TEST_PASSWORD, "cannot read the key file"),
        (["--sm4-key-hex", SOME_KEY_HEX], "", "standard input"),
        (["--sm4-key-hex", SOME_KEY_HEX], "12345\n", "too weak"),
        (["--sm4-key-hex", SOME_KEY_HEX, "--username", "bad name!"], TEST_PASSWORD, "username"),
    ],
)
def test_owner_create_refuses_bad_input_and_creates_nothing(deployed, args, password, message):
    if "--username" not in args:
        args = ["--username", "alice", *args]
    with pytest.raises(CommandError, match=message):
        _owner_create(*args, password=password)
    assert not Owner.objects.exists()


def test_the_password_is_never_taken_from_the_command_line(deployed):
    with pytest.raises(CommandError, match="unrecognized arguments"):
        _owner_create("--username", "alice", "--sm4-key-hex", SOME_KEY_HEX, "--password", "x")
    assert not Owner.objects.exists()


def test_owner_create_refuses_a_taken_username(deployed):
    _owner_create("--username", "alice", "--sm4-key-hex", sm4.generate_key().hex())
    with pytest.raises(CommandError, match="taken"):
        _owner_create("--username", "alice", "--sm4-key-hex", sm4.generate_key().hex())
    assert Owner.objects.count() == 1


def test_owner_create_before_the_contract_is_deployed_creates_nothing(db):
    with pytest.raises(CommandError, match="nothing was created"):
        _owner_create("--username", "alice", "--sm4-key-hex", sm4.generate_key().hex())
    assert not Owner.objects.exists()


def test_owner_create_says_when_the_chain_did_not_confirm_in_time(deployed, settings):
    # More than the operator holds (within the budget): funding the EOA cannot succeed.
    settings.CHAIN_EOA_FUNDING_GAS = settings.CHAIN_EOA_FUNDING_WEI = 10**30
    settings.SIGNUP_FUNDING_BUDGET_WEI = 10**31
    with pytest.raises(CommandError, match="was created but is not registered"):
        _owner_create(
            "--username", "alice", "--sm4-key-hex", sm4.generate_key().hex(), "--timeout", "1"
        )
    assert Owner.objects.get().chain_state == ChainState.PENDING


def test_robot_create_prints_the_id_and_a_working_token(make_owner):
    owner = make_owner("alice")
    result = _robot_create("--owner", "alice", "--name", "turtlebot-1")
    robot = Robot.objects.get(pk=result["robot"])
    assert result == {
        "robot": str(robot.id),
        "token": result["token"],
        "name": "turtlebot-1",
        "owner": "alice",
        "owner_address": owner.eoa_address,
        "owner_chain_state": "confirmed",
    }
    assert robot_by_token(result["token"]) == robot
    by_address = _robot_create("--owner", owner.eoa_address.lower(), "--name", "turtlebot-2")
    assert by_address["owner"] == "alice"


def test_robot_create_refuses_unknown_owners_and_taken_names(make_owner):
    make_owner("alice")
    _robot_create("--owner", "alice", "--name", "turtlebot-1")
    with pytest.raises(CommandError, match="no owner 'bob'"):
        _robot_create("--owner", "bob", "--name", "turtlebot-1")
    with pytest.raises(CommandError, match="already has a robot named"):
        _robot_create("--owner", "alice", "--name", "turtlebot-1")
    with pytest.raises(CommandError, match="1 to 100 characters"):
        _robot_create("--owner", "alice", "--name", "   ")
    assert Robot.objects.count() == 1


@pytest.mark.process
def test_the_commands_as_an_operator_runs_them_against_anvil(tmp_path):
    """Fresh processes, a real node, the password piped on standard input."""
    with start_anvil() as node:
        env = {
            **os.environ,
            "CHAIN_RPC_URL": node.url,
            "AUTHROS_VAR_DIR": str(tmp_path),
            "DATABASE_URL": f"sqlite:///{tmp_path / 'db.sqlite3'}",
            "LOG_LEVEL": "WARNING",
        }

        def manage(*args: str, stdin: str = "") -> subprocess.CompletedProcess:
            return subprocess.run(
                [sys.executable, "manage.py", *args],
                cwd=REPO_ROOT,
                env=env,
                input=stdin,
                capture_output=True,
                text=True,
                timeout=180,
                check=False,
            )

        assert manage("migrate", "--noinput").returncode == 0
        assert manage("chain_deploy").returncode == 0
        key = sm4.generate_key().hex()
        created = manage(
            "owner_create", "--username", "alice", "--sm4-key-hex", key, stdin=TEST_PASSWORD
        )
        assert created.returncode == 0, created.stderr
        owner = json.loads(created.stdout)
        assert owner["chain_state"] == "confirmed"
        assert owner["address"].startswith("0x")
        assert TEST_PASSWORD not in created.stdout + created.stderr

        robot = manage("robot_create", "--owner", "alice", "--name", "turtlebot-1")
        assert robot.returncode == 0, robot.stderr
        assert json.loads(robot.stdout)["owner"] == "alice"

        again = manage("robot_create", "--owner", "alice", "--name", "turtlebot-1")
        assert again.returncode != 0
        assert "already has a robot named" in again.stderr


def test_demo_setup_makes_the_owner_once_and_no_robot(deployed, tmp_path):
    """The demo robot is paired by `make run` (tests/accounts/test_pairing_commands.py), not
    made here: no key file, no token file."""
    folder = tmp_path / "demo"
    args = ("demo_setup", "--dir", str(folder), "--portal-url", "http://127.0.0.1:8123")
    out = StringIO()
    call_command(*args, stdout=out)
    first = json.loads(out.getvalue())
    owner = Owner.objects.get(user__username=first["username"])
    assert owner.chain_state == ChainState.CONFIRMED
    assert first["eoa"] == owner.eoa_address
    assert first["robot_paired"] is False
    assert first["agent_config"] == str(folder / "robot" / "agent.yaml")
    assert (folder / "password").stat().st_mode & 0o777 == 0o600
    assert sorted(path.name for path in folder.iterdir()) == ["password"]

    again = StringIO()
    call_command(*args, stdout=again)
    assert json.loads(again.getvalue()) == first
    assert not Robot.objects.exists()
