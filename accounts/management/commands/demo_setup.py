"""`manage.py demo_setup --dir var/demo`: a demo owner for `make run`, and whether its robot is
paired.

Used by `make run`. Idempotent: the owner is created once (its SM4 key generated and kept by
the portal only: the demo robot receives it by pairing, like any robot) and its password lives
in a 0600 file in --dir. The robot is not made here: `make run` pairs it (`python -m ros_agent
pair --dir DIR/robot`, approved with `manage.py robot_pair_approve`). Prints JSON with the
owner's username, password file, EOA, the robot's folder and config, and `robot_paired`: whether
that config's token still works (else `make run` pairs the robot again).
"""

import json
import os
import secrets
from pathlib import Path
from typing import Any

import yaml
from django.core.management.base import BaseCommand, CommandError, CommandParser

from accounts.models import ChainState
from accounts.selectors import owner_by_username, robot_by_token
from accounts.services.keys import sm4_key_generate
from accounts.services.owners import owner_create
from accounts.services.registration import owner_register_on_chain
from chainworker.errors import ChainError

ROBOT_FOLDER = "robot"


class Command(BaseCommand):
    help = "Create (once) a demo owner; say whether its robot's pairing still holds."

    def add_arguments(self, parser: CommandParser) -> None:
        parser.add_argument("--dir", default="var/demo", help="where the 0600 files go")
        parser.add_argument("--portal-url", default="http://127.0.0.1:8000")
        parser.add_argument("--username", default="demo")

    def handle(self, *args: Any, **options: Any) -> None:
        folder = Path(options["dir"]).resolve()
        folder.mkdir(mode=0o700, parents=True, exist_ok=True)
        username = options["username"]
        owner = owner_by_username(username)
        if owner is None:
            password = secrets.token_urlsafe(12)
            owner = owner_create(username=username, password=password, sm4_key=sm4_key_generate())
            _write_private(folder / "password", password)
        elif not (folder / "password").exists():
            raise CommandError(
                f"owner {username!r} exists but {folder / 'password'} is gone: "
                "use another --username or --dir"
            )
        if owner.chain_state != ChainState.CONFIRMED:
            try:
                owner = owner_register_on_chain(owner_id=owner.pk)
            except ChainError as exc:
                raise CommandError(f"could not register {username} on chain: {exc}") from exc
        robot_folder = folder / ROBOT_FOLDER
        config = robot_folder / "agent.yaml"
        self.stdout.write(
            json.dumps(
                {
                    "username": username,
                    "password_file": str(folder / "password"),
                    "eoa": owner.eoa_address,
                    "robot_dir": str(robot_folder),
                    "agent_config": str(config),
                    "robot_paired": _paired_with(config, owner.username, options["portal_url"]),
                },
                sort_keys=True,
            )
        )


def _paired_with(config: Path, username: str, portal_url: str) -> bool:
    """Whether the robot's config is a pairing with this owner, on this portal, whose token
    still works."""
    try:
        settings = yaml.safe_load(config.read_text())
        token = (config.parent / settings["token_file"]).read_text().strip()
    except (OSError, yaml.YAMLError, KeyError, TypeError):
        return False
    robot = robot_by_token(token)
    return (
        robot is not None
        and bool(robot.public_key)
        and robot.owner.username == username
        and settings.get("portal_url") == portal_url.rstrip("/")
    )


def _write_private(path: Path, text: str) -> None:
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "w") as handle:
        handle.write(text + "\n")
    os.chmod(path, 0o600)
