"""`manage.py demo_setup --dir var/demo --portal-url URL`: a demo owner, robot and agent config.

Used by `make run`. Idempotent: the owner is created once; the robot token and the owner's
key live in 0600 files in --dir, and a new robot is made only when its token file is gone.
Prints JSON with the owner's username, password file, EOA, robot id and the agent config path.
"""

import json
import os
import secrets
from pathlib import Path
from typing import Any

from django.core.management.base import BaseCommand, CommandError, CommandParser
from django.utils import timezone

from accounts.agent_config import DEFAULT_TOPICS, agent_config_yaml
from accounts.models import ChainState
from accounts.selectors import owner_by_username, robot_by_token
from accounts.services import (
    owner_create,
    owner_register_on_chain,
    robot_create,
    sm4_key_generate,
)
from chainworker.chain import ChainError

# The demo agent sends often, so the simulated robot's data shows up within a second.
DEMO_AGENT_OPTIONS = {"batch_size": 20, "flush_interval": 1.0, "spool_dir": "spool"}


class Command(BaseCommand):
    help = "Create (once) a demo owner with a robot, and write the robot's agent config."

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
            key = sm4_key_generate()
            password = secrets.token_urlsafe(12)
            owner = owner_create(username=username, password=password, sm4_key=key)
            _write_private(folder / "sm4.key", key.hex())
            _write_private(folder / "password", password)
        elif not (folder / "sm4.key").exists():
            raise CommandError(
                f"owner {username!r} exists but {folder / 'sm4.key'} is gone: "
                "use another --username or --dir"
            )
        if owner.chain_state != ChainState.CONFIRMED:
            try:
                owner = owner_register_on_chain(owner_id=owner.pk)
            except ChainError as exc:
                raise CommandError(f"could not register {username} on chain: {exc}") from exc
        token_file = folder / "robot.token"
        config_file = folder / "agent.yaml"
        token = token_file.read_text().strip() if token_file.exists() else ""
        if not config_file.exists() or robot_by_token(token) is None:
            robot, token = robot_create(owner=owner, name=f"demo-robot-{secrets.token_hex(3)}")
            _write_private(token_file, token)
            config_file.write_text(
                agent_config_yaml(
                    portal_url=options["portal_url"],
                    robot_id=str(robot.pk),
                    robot_name=robot.name,
                    owner_username=username,
                    topics=DEFAULT_TOPICS,
                    token=None,
                    made_at=timezone.now(),
                    key_file="sm4.key",
                    options=DEMO_AGENT_OPTIONS,
                )
            )
        self.stdout.write(
            json.dumps(
                {
                    "username": username,
                    "password_file": str(folder / "password"),
                    "eoa": owner.eoa_address,
                    "agent_config": str(config_file),
                },
                sort_keys=True,
            )
        )


def _write_private(path: Path, text: str) -> None:
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "w") as handle:
        handle.write(text + "\n")
    os.chmod(path, 0o600)
