"""`manage.py chain_resync [--yes]`: re-create everything on chain from the database."""

import json
from typing import Any

from django.core.management.base import BaseCommand, CommandError, CommandParser

from chainworker.errors import ChainError
from chainworker.services import chain_identity
from chainworker.work import ChainWorkNotReady
from sharing.services.reconcile import chain_resync


class Command(BaseCommand):
    help = (
        "Re-create everything on chain from the database after a chain reset: deploy the "
        "contract if the chain has none, then register every owner again (fund, enroll, "
        "register, rotate), re-send active grants and anchor every record again. "
        "What is on chain already is skipped."
    )

    def add_arguments(self, parser: CommandParser) -> None:
        parser.add_argument("--yes", action="store_true", help="do not ask for confirmation")
        parser.add_argument("--json", action="store_true", help="print what was queued as JSON")

    def handle(self, *args: Any, **options: Any) -> None:
        try:
            identity = chain_identity()
            if not options["yes"]:
                where = f"chain identity: {identity.state}" + (
                    f" ({identity.reason})" if identity.reason else ""
                )
                self.stdout.write(where)
                answer = input("Re-create every owner, grant and record on chain? [y/N] ")
                if answer.strip().lower() not in ("y", "yes"):
                    raise CommandError("cancelled: nothing was changed")
            counts = chain_resync()
        except ChainWorkNotReady as exc:
            raise CommandError(f"a reconciliation is under way, try again: {exc}") from exc
        except ChainError as exc:
            raise CommandError(f"chain unavailable: {exc}") from exc
        if options["json"]:
            self.stdout.write(json.dumps(counts, sort_keys=True))
            return
        if "deployed" in counts:
            self.stdout.write(f"Deployed AuthROS at {counts['deployed']}")
        self.stdout.write(
            self.style.SUCCESS(
                f"Queued: {counts['owners']} owner registration(s), {counts['grants']} grant(s), "
                f"{counts['records']} record(s) to anchor again"
            )
        )
