"""`manage.py chain_deploy [--force]`: deploy the AuthROS contract once and record it."""

import json
from typing import Any

from django.core.management.base import BaseCommand, CommandError, CommandParser

from chainworker.errors import ChainError
from chainworker.services import contract_deploy


class Command(BaseCommand):
    help = "Deploy the AuthROS contract (idempotent) and record its address."

    def add_arguments(self, parser: CommandParser) -> None:
        parser.add_argument(
            "--force", action="store_true", help="deploy a new contract even if one is recorded"
        )
        parser.add_argument("--json", action="store_true", help="print the result as JSON")

    def handle(self, *args: Any, **options: Any) -> None:
        try:
            outcome = contract_deploy(force=options["force"])
        except ChainError as exc:
            raise CommandError(f"deployment failed: {exc}") from exc
        d = outcome.deployment
        result = {
            "address": d.address,
            "chain_id": d.chain_id,
            "block_number": d.block_number,
            "tx_hash": d.tx_hash,
            "admin": d.deployer,
            "created": outcome.created,
            "reason": outcome.reason,
        }
        if options["json"]:
            self.stdout.write(json.dumps(result, sort_keys=True))
        elif outcome.created:
            self.stdout.write(
                self.style.SUCCESS(
                    f"Deployed AuthROS at {d.address} ({outcome.reason}), "
                    f"block {d.block_number}, tx {d.tx_hash}"
                )
            )
        else:
            self.stdout.write(f"AuthROS already deployed at {d.address} (block {d.block_number})")
