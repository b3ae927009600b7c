"""`manage.py robot_create --owner U --name N`: a robot and its API token, printed as JSON.

The token is shown once; only its hash is stored. Put it in the agent's `token_file`.
"""

import json
from typing import Any

from django.core.management.base import BaseCommand, CommandError, CommandParser

from accounts.errors import AccountError
from accounts.selectors import owner_by_identifier
from accounts.services.robots import robot_create


class Command(BaseCommand):
    help = "Create a robot for an owner and print its id and token (shown only once) as JSON."

    def add_arguments(self, parser: CommandParser) -> None:
        parser.add_argument("--owner", required=True, help="the owner's username or 0x address")
        parser.add_argument("--name", required=True, help="the robot's name, unique per owner")

    def handle(self, *args: Any, **options: Any) -> None:
        owner = owner_by_identifier(options["owner"])
        if owner is None:
            raise CommandError(
                f"no owner {options['owner'].strip()!r}: create it with `manage.py owner_create`"
            )
        try:
            robot, token = robot_create(owner=owner, name=options["name"])
        except AccountError as exc:
            raise CommandError(str(exc)) from exc
        result = {
            "robot": str(robot.id),
            "token": token,
            "name": robot.name,
            "owner": owner.username,
            "owner_address": owner.eoa_address,
            "owner_chain_state": owner.chain_state,
        }
        self.stdout.write(json.dumps(result, sort_keys=True))
