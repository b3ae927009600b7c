"""`manage.py robot_pair_approve --owner U --code C [--name N] [--refuse]`: answer a robot's
pairing request for its owner, as the owner does on the robots page; prints JSON.

For provisioning without a browser (and for `make run`'s demo robot, which has no human to type
its code). Whoever runs it acts for the owner: check the code and the fingerprint it prints
against what the robot printed (`python -m ros_agent pair`).
"""

import json
from typing import Any

from django.core.management.base import BaseCommand, CommandError, CommandParser

from accounts.errors import AccountError
from accounts.selectors import owner_by_identifier, pairing_code_display, public_key_fingerprint
from accounts.services.pairing import robot_pairing_answer


class Command(BaseCommand):
    help = "Approve (or refuse) a robot's pairing request by the code it printed."

    def add_arguments(self, parser: CommandParser) -> None:
        parser.add_argument("--owner", required=True, help="the owner's username or 0x address")
        parser.add_argument("--code", required=True, help="the code the robot printed")
        parser.add_argument("--name", help="the robot's name (default: the one it asked with)")
        parser.add_argument("--refuse", action="store_true", help="refuse instead of approving")

    def handle(self, *args: Any, **options: Any) -> None:
        owner = owner_by_identifier(options["owner"])
        if owner is None:
            raise CommandError(f"no owner {options['owner'].strip()!r}")
        try:
            pairing = robot_pairing_answer(
                owner=owner,
                code=options["code"],
                approve=not options["refuse"],
                actor=None,
                name=options["name"],
            )
        except AccountError as exc:
            raise CommandError(f"{exc.code}: {exc}") from exc
        result = {
            "state": pairing.state,
            "code": pairing_code_display(pairing.code),
            "fingerprint": public_key_fingerprint(pairing.public_key),
            "owner": owner.username,
            "robot": str(pairing.robot_id) if pairing.robot_id else None,
            "name": pairing.robot.name if pairing.robot else pairing.name,
        }
        self.stdout.write(json.dumps(result, sort_keys=True))
